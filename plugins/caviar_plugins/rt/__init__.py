"""Ray tracing, in one home: every module that traces rays in a Sionna RT scene does it
through this package.

* :mod:`~caviar_plugins.rt.drjit_setup`: Dr.Jit's libLLVM and thread count;
* :mod:`~caviar_plugins.rt.sionna_adapter`: the only user of Sionna RT's and Sionna SYS's
  private names;
* :mod:`~caviar_plugins.rt.scene`: loading a scene, the objects that move in it, its
  vertex positions, what a ray meets first;
* :mod:`~caviar_plugins.rt.scatterers`: pools of boxes for vehicles and persons;
* :mod:`~caviar_plugins.rt.solver`: :class:`PathTracer`, Sionna's path solver with the
  shoot cache and the path-buffer watch;
* :mod:`~caviar_plugins.rt.shoot_cache`: the shoot cache, one module per phase.

The radio link (:class:`caviar_plugins.radio.RadioScene`), the network's site tracer
(:class:`caviar_plugins.network.raytraced.SiteTracer`), its radio map and the traffic link
are clients of it. Importing this package imports neither Sionna nor Dr.Jit.
"""

from caviar_plugins.rt.drjit_setup import configure_drjit, set_thread_count

__all__ = ["configure_drjit", "set_thread_count"]
