"""Stand-in (scripts/gpu-standins): Sionna RT imports IPython for its notebook previewer only."""

version_info = (8, 0, 0)


def get_ipython():
    """No IPython kernel here (what the real one says outside a notebook)."""
    return None
