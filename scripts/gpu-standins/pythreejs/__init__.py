"""Stand-in (scripts/gpu-standins): Sionna RT imports pythreejs for its notebook previewer only.

Every public name is a placeholder class, so that annotations and base classes naming one
(``p3s.PerspectiveCamera`` in ``rt/viewer.py``) evaluate; making one fails, saying why."""


class Placeholder:
    def __init__(self, *args, **kwargs):
        raise RuntimeError(f"pythreejs.{type(self).__name__}: a stand-in (scripts/gpu-standins); "
                           "no notebook previewer on this machine")


def __getattr__(name):
    if name.startswith("__"):  # (module protocol: __path__, __all__...)
        raise AttributeError(name)
    cls = type(name, (Placeholder,), {"__module__": __name__})
    globals()[name] = cls
    return cls
