"""Physical constants (SI, exact), in a module that imports nothing: the radio models, the
network and the paper's protocol all use them."""

BOLTZMANN = 1.380649e-23
"""J/K."""
SPEED_OF_LIGHT = 299_792_458.0
"""m/s."""
