"""Stand-in (scripts/gpu-standins): Sionna RT imports ipywidgets for its notebook previewer only.

Every public name (also under ``ipywidgets.widgets``) is a placeholder class; making one fails,
saying why."""

import sys
import types


class Placeholder:
    def __init__(self, *args, **kwargs):
        raise RuntimeError(f"ipywidgets.{type(self).__name__}: a stand-in (scripts/gpu-standins); "
                           "no notebook previewer on this machine")


def __getattr__(name):
    if name.startswith("__"):  # (module protocol: __path__, __all__...)
        raise AttributeError(name)
    cls = type(name, (Placeholder,), {"__module__": __name__})
    globals()[name] = cls
    return cls


widgets = types.ModuleType(f"{__name__}.widgets", "Stand-in: the same placeholders.")
widgets.__getattr__ = __getattr__  # type: ignore[attr-defined]
sys.modules[widgets.__name__] = widgets
