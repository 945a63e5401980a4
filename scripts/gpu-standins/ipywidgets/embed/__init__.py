"""Stand-in (scripts/gpu-standins)."""


def embed_snippet(*args, **kwargs):
    raise RuntimeError("ipywidgets.embed.embed_snippet: a stand-in (scripts/gpu-standins); no notebook on this machine")
