"""The path solver every ray-traced module uses: Sionna RT's ``PathSolver`` with the shoot
cache (:mod:`~caviar_plugins.rt.shoot_cache`) standing in for its candidate generator, and a
watch on its path buffer (NVlabs/sionna#1172: candidates beyond ``max_num_paths_per_src``
are dropped silently; :class:`PathTracer` counts them and warns).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.scene import MovingObjects
from caviar_plugins.rt.shoot_cache import ShootCache

DEFAULT_MAX_PATHS_PER_SOURCE = 1_000_000
"""Sionna's own default for ``max_num_paths_per_src``."""

SHOOT_CACHE_SETTINGS = (True, False, "auto")


def check_shoot_cache(value: bool | str, key: str = "shoot_cache") -> bool | str:
    """``value`` if it is a shoot-cache setting (true, false or ``"auto"``), else a
    ValueError naming ``key``."""
    if isinstance(value, bool) or value == "auto":
        return value
    raise ValueError(f'{key}: expected true, false or "auto", got {value!r}')


def use_shoot_cache(setting: bool | str, variant: str | None = None) -> bool:
    """Whether a setting turns the shoot cache on. ``"auto"`` chooses by Dr.Jit backend, from
    measurements: on for LLVM (the CPU), where a cached solve costs 0.08x of Sionna's loop for
    1 receiver and 0.36x for 10 (2 cores); off for CUDA, where on one H100 it measured 1.29x
    (1 UAV), 2.79x (10 UAVs) and 1.38x (a moving body) of Sionna's loop, the solve being bound
    by host work there (docs/tutorials/gpu-machine.md). ``variant``: the Mitsuba variant
    (default: the active one)."""
    check_shoot_cache(setting)
    if setting != "auto":
        return bool(setting)
    if variant is None:
        from caviar_plugins.rt.drjit_setup import mitsuba

        variant = str(mitsuba().variant())
    return not variant.startswith("cuda_")  # (cuda_ad_rgb, cuda_ad_mono_polarized...)


class PathTracer:
    """Sionna's ``PathSolver`` for ``scene``, with the shoot cache (``shoot_cache``: true, false
    or ``"auto"``, see :func:`use_shoot_cache`) and the path-buffer watch. ``movers``
    (optional) are the objects that move on top of the cache's recorded bounces; without it
    every moved object is a new geometry.

    Where the installed Sionna RT lacks an internal the cache or the watch use
    (:func:`~caviar_plugins.rt.sionna_adapter.problem`), it warns once and runs Sionna's own
    loop, unwatched: correct, slower."""

    def __init__(self, scene: Any, shoot_cache: bool | str = "auto", movers: MovingObjects | None = None,
                 max_num_paths_per_src: int = DEFAULT_MAX_PATHS_PER_SOURCE):
        import sionna.rt as rt

        shoot_cache = use_shoot_cache(shoot_cache)

        if max_num_paths_per_src < 1:
            raise ValueError(f"max_num_paths_per_src: expected >= 1, got {max_num_paths_per_src}")
        self.scene = scene
        self.movers = movers if movers is not None else MovingObjects(scene, enabled=False)
        self.max_num_paths_per_src = max_num_paths_per_src
        self.solver = rt.PathSolver()
        self.shoot_cache: ShootCache | None = None
        self.last_paths: Any = None
        """Sionna's ``Paths`` of the last solve."""
        self.dropped = 0
        """Candidates the last solve dropped for lack of path buffer."""
        self._counter: Any = None
        problem = adapter.problem()
        if problem is not None:
            warnings.warn(f"{problem}: Sionna's own shoot-and-bounce runs"
                          f"{' (shoot_cache = true ignored)' if shoot_cache else ''}, and candidates dropped "
                          "for lack of path buffer are not reported", RuntimeWarning, stacklevel=3)
            return
        adapter.watch_candidate_counter(self.solver, self._saw_counter)
        if shoot_cache:
            movers_ = self.movers
            self.shoot_cache = ShootCache(adapter.candidate_generator(self.solver), movers_.fingerprint,
                                          movers=movers_.present, scene=scene, rays_for=movers_.rays_at,
                                          boxes_of=movers_.boxes_of)
            adapter.replace_candidate_generator(self.solver, self.shoot_cache)

    def _saw_counter(self, counter) -> None:
        """Keeps the per-source candidate counter of Sionna's shoot-and-bounce (incremented
        for every candidate *before* the cap)."""
        self._counter = counter

    @property
    def cache_seen(self) -> bool:
        """Whether the shoot cache saw the last solve's geometry (the next solve of it is
        served from the cache): what a checkpoint keeps of the tracer."""
        return self.shoot_cache is not None and self.shoot_cache.has_seen_geometry

    def paths_dropped(self) -> int:
        """Candidates the last solve dropped for lack of buffer (0: none)."""
        counter = self._counter
        if self.shoot_cache is not None and self.shoot_cache.paths_counter_per_source is not None:
            counter = self.shoot_cache.paths_counter_per_source
        if counter is None:
            return 0
        counts = np.array(counter, dtype=np.int64).reshape(-1)
        return int(np.maximum(counts - self.max_num_paths_per_src, 0).sum())

    def solve(self, **options: Any) -> Any:
        """One solve of every source toward every receiver of the scene: Sionna's
        ``PathSolver`` keywords (``max_depth``, ``samples_per_src``, ``synthetic_array``,
        the interaction flags, ``seed``...). Warns when the path buffer overflowed
        (:attr:`dropped` says by how much). Returns Sionna's ``Paths``."""
        paths = self.last_paths = self.solver(self.scene, max_num_paths_per_src=self.max_num_paths_per_src,
                                              **options)
        self.dropped = self.paths_dropped()
        if self.dropped:
            warnings.warn(f"Sionna's path buffer overflowed: {self.dropped} candidate paths dropped "
                          f"(max_num_paths_per_src = {self.max_num_paths_per_src}); raise it", RuntimeWarning,
                          stacklevel=3)
        return paths

    def cache_status(self, solves: int) -> str | None:
        """One line on what share of ``solves`` the shoot cache served (None without it or
        before the first solve)."""
        if self.shoot_cache is None or not solves:
            return None
        return f"shoot cache {100 * self.shoot_cache.connects / solves:.0f} % of {solves} solves"
