"""Ray tracing, in one home: every module that traces rays in a Sionna RT scene does it
through this package, the only one that imports Sionna RT (checked by
tests/test_rt_front_door.py).

* :mod:`~caviar_plugins.rt.settings`: :class:`TraceSettings`, the ``raytracing = { … }``
  table of every module that traces (rays, depth, interactions, seed, threads, cache);
* :mod:`~caviar_plugins.rt.scene`: :func:`~caviar_plugins.rt.scene.build_scene`, the one way
  to get a scene (loaded, with its carrier, arrays and transmitters), the objects that move
  in it, its vertex positions, what a ray meets first;
* :mod:`~caviar_plugins.rt.solver`: :class:`~caviar_plugins.rt.solver.PathTracer`, Sionna's
  path solver with the shoot cache and the path-buffer watch, and the radio-map solver;
* :mod:`~caviar_plugins.rt.drjit_setup`: Dr.Jit's libLLVM and thread count;
* :mod:`~caviar_plugins.rt.sionna_adapter`: the only user of Sionna RT's private names
  (Sionna SYS's: :mod:`caviar_plugins.radio.sionna_sys_adapter`);
* :mod:`~caviar_plugins.rt.scatterers`: pools of boxes for vehicles and persons;
* :mod:`~caviar_plugins.rt.shoot_cache`: the shoot cache, one module per phase.

The SAR link (:class:`caviar_plugins.radio.RadioScene`), the traffic link, the network's site
tracer (:class:`caviar_plugins.network.raytraced.SiteTracer`) and radio map, the LiDAR and the
DeepMIMO export are its clients. ``samples_per_src`` goes from the TOML to Sionna in three
hops: the plugin's ``raytracing`` table (a :class:`TraceSettings`), the
:class:`~caviar_plugins.rt.solver.PathTracer` that holds it, Sionna's ``PathSolver`` call.
Importing this package imports neither Sionna nor Dr.Jit.
"""

from caviar_plugins.rt.drjit_setup import configure_drjit, set_thread_count
from caviar_plugins.rt.settings import TraceSettings, with_raytracing

__all__ = ["TraceSettings", "configure_drjit", "set_thread_count", "with_raytracing"]
