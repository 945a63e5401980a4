"""Stand-in (scripts/gpu-standins): display does nothing, there being no notebook to show in."""


def display(*args, **kwargs):
    return None


class HTML:
    def __init__(self, data=None, *args, **kwargs):
        self.data = data
