"""The path solver every ray-traced module uses: Sionna RT's ``PathSolver`` with the shoot
cache (:mod:`~caviar_plugins.rt.shoot_cache`) standing in for its candidate generator, and a
watch on its path buffer (NVlabs/sionna#1172: candidates beyond ``max_num_paths_per_src``
are dropped silently; :class:`PathTracer` counts them and warns) and on its table of the
specular chains seen (a chain whose hash collides is dropped silently: where a solve by
Sionna's loop found more candidates than the table holds with under 1 % lost, it is solved
again with a larger one, :func:`~caviar_plugins.rt.sionna_adapter.chain_table_slots`).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from caviar_plugins.rt import sionna_adapter as adapter
from caviar_plugins.rt.drjit_setup import jit
from caviar_plugins.rt.scene import MovingObjects
from caviar_plugins.rt.settings import TraceSettings, check_shoot_cache
from caviar_plugins.rt.shoot_cache import ShootCache


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
    """Sionna's ``PathSolver`` for ``scene``, traced as ``settings`` say (rays, depth,
    interactions, the solver's seed: ``settings.seed`` or the run's ``seed``), with the shoot
    cache (``settings.shoot_cache``: true, false or ``"auto"``, see :func:`use_shoot_cache`)
    and the path-buffer watch (``settings.max_num_paths_per_src``). ``movers`` (optional)
    are the objects that move on top of the cache's recorded bounces; without it every
    moved object is a new geometry.

    Where the installed Sionna RT lacks an internal the cache or the watch use
    (:func:`~caviar_plugins.rt.sionna_adapter.problem`), it warns once and runs Sionna's own
    loop, unwatched: correct, slower."""

    def __init__(self, scene: Any, settings: TraceSettings, seed: int = 0, movers: MovingObjects | None = None):
        import sionna.rt as rt

        shoot_cache = use_shoot_cache(settings.shoot_cache)
        self.scene = scene
        self.settings = settings
        self.options = settings.path_options(seed)
        """The keywords every solve passes to Sionna's ``PathSolver``."""
        self.movers = movers if movers is not None else MovingObjects(scene, enabled=False)
        self.max_num_paths_per_src = settings.max_num_paths_per_src
        self.solver = rt.PathSolver()
        self.shoot_cache: ShootCache | None = None
        self.last_paths: Any = None
        """Sionna's ``Paths`` of the last solve."""
        self.dropped = 0
        """Candidates the last solve dropped for lack of path buffer."""
        self._counter: Any = None
        self.chain_slots = 0
        """Slots per source of Sionna's specular-chain tables (0: its own, 1e6); grown when a
        solve finds more candidates than they hold without collisions (:meth:`solve`)."""
        self.chain_loss = 0.0
        """The share of specular chains the last solve lost to collisions, to first order."""
        self._chain_warned = False
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

    def solve(self, synthetic_array: bool = True) -> Any:
        """One solve of every source toward every receiver of the scene, with :attr:`options`
        (``synthetic_array``: the arrays' channels from their centres' paths). Warns when
        the path buffer overflowed (:attr:`dropped` says by how much). Returns Sionna's
        ``Paths``."""
        while True:
            with adapter.chain_table(self.chain_slots):
                paths = self.last_paths = self.solver(self.scene, max_num_paths_per_src=self.max_num_paths_per_src,
                                                      synthetic_array=synthetic_array, **self.options)
            if not self._chain_table_grown():
                break
        self.dropped = self.paths_dropped()
        if self.dropped:
            warnings.warn(f"Sionna's path buffer overflowed: {self.dropped} candidate paths dropped "
                          f"(raytracing.max_num_paths_per_src = {self.max_num_paths_per_src}); raise it",
                          RuntimeWarning, stacklevel=3)
        return paths

    def _chain_table_grown(self) -> bool:
        """After a solve by Sionna's own loop: whether it found more candidates a source than
        its specular-chain tables hold without losing over
        :data:`~caviar_plugins.rt.sionna_adapter.CHAIN_LOSS` of them to collisions, and the
        tables were grown for a new solve (a solve the shoot cache served is deduplicated
        exactly; its first solve of a geometry is Sionna's loop)."""
        served = self.shoot_cache is not None and self.shoot_cache.paths_counter_per_source is not None
        if served or self._counter is None:
            return False
        counts = np.array(self._counter, dtype=np.int64).reshape(-1)
        found = int(min(counts.max(initial=0), self.max_num_paths_per_src))
        self.chain_loss, size, grown = adapter.chain_table_check(found, self.max_num_paths_per_src, self.chain_slots,
                                                                 len(counts))
        if grown:
            self.chain_slots = grown
            return True
        if self.chain_loss > adapter.CHAIN_LOSS and not self._chain_warned:
            self._chain_warned = True
            warnings.warn(adapter.chain_loss_warning(self.chain_loss, size, "fewer rays or receivers a solve, or the "
                                                     "shoot cache, which deduplicates exactly"),
                          RuntimeWarning, stacklevel=4)
        return False

    def cache_status(self, solves: int) -> str | None:
        """One line on what share of ``solves`` the shoot cache served (None without it or
        before the first solve)."""
        if self.shoot_cache is None or not solves:
            return None
        return f"shoot cache {100 * self.shoot_cache.connects / solves:.0f} % of {solves} solves"


def radio_map(scene: Any, settings: TraceSettings, seed: int, *, center: Any, size: Any, cell_size: Any) -> Any:
    """Sionna RT's radio map of ``scene`` on a horizontal grid: ``center`` (x, y, z), ``size``
    (x, y) and ``cell_size`` (x, y) in metres, traced as ``settings`` say (the solver's seed:
    ``settings.seed`` or the run's ``seed``). Returns Sionna's ``RadioMap``."""
    import sionna.rt as rt

    _, mi = jit()
    return rt.RadioMapSolver()(scene, center=mi.Point3f(*(float(v) for v in center)),
                               orientation=mi.Point3f(0.0, 0.0, 0.0), size=mi.Point2f(*(float(v) for v in size)),
                               cell_size=mi.Point2f(*(float(v) for v in cell_size)), **settings.map_options(seed))


def carrier_sums(a_re, a_im, tau, n_paths, n_ant, frequency, n_out: int):
    """Σ_p a·exp(−j2π f τ_p) per (receiver, antenna pair) from the flat arrays of a
    synthetic-array solve (a: [rx, rx_ant, 1, tx_ant, P], τ: [rx, 1, P]), with Sionna's
    float32 carrier phase (``Paths.cir``: a delay of −1 counts as 0, the phase mapped to
    [0, 2π)). One lane per (receiver, antenna pair) loops over the paths in order, so a
    receiver's sum is the same whatever the other receivers of the solve (their padding
    adds exact zeros); the path count P is opaque: the kernel's code is the same whatever it is."""
    dr, mi = jit()
    row = dr.arange(mi.UInt, n_out)
    base, tau_base = row * n_paths, (row // n_ant) * n_paths
    two_pi = 2 * dr.pi

    def body(p, h_re, h_im):
        t = dr.gather(mi.Float, tau, tau_base + p)
        t = dr.select(t == -1, 0, t)
        phase = (-two_pi * frequency) * t
        phase = phase - two_pi * dr.floor(phase * (1 / two_pi))
        s, c = dr.sincos(phase)
        re, im = dr.gather(mi.Float, a_re, base + p), dr.gather(mi.Float, a_im, base + p)
        return p + 1, h_re + (re * c - im * s), h_im + (re * s + im * c)

    _, h_re, h_im = dr.while_loop((dr.zeros(mi.UInt, n_out), dr.zeros(mi.Float, n_out), dr.zeros(mi.Float, n_out)),
                                  lambda p, h_re, h_im: p < n_paths, body)
    return h_re, h_im


FROZEN: dict[str, Any] = {}
"""The frozen functions of this module (``carrier``: :func:`carrier_sums` under ``dr.freeze``)."""


CARRIER_METHODS = ("auto", "frozen", "cfr")
"""How :func:`carrier_channels` sums: ``frozen`` (one kernel under ``dr.freeze``), ``cfr``
(Sionna's ``paths.cfr``) or ``auto``: ``frozen`` on Dr.Jit's LLVM backend, ``cfr`` on CUDA."""


def carrier_channels(paths: Any, n_rx: int, frequency_hz: float,
                     method: str = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The narrowband channel at the carrier of every receiver of a synthetic-array solve
    from one transmitter, H = Σ a·exp(−j2π f_c τ) (N_rx, N_rx_ant, N_tx_ant) complex64, and
    the paths' validity and delays (N_rx, P): Sionna's ``paths.cfr`` at baseband offset 0
    (equal to it to 3e-7), without its kernels, whose code changed with the number of
    paths (a compilation per solve on the CPU). The sum runs in one kernel under
    ``dr.freeze`` (:func:`carrier_sums`: recorded once, replayed whatever the path count;
    host time in benches/bench_solve_host.py), and H, validity and delays come back in one read.
    ``frequency_hz``: the scene's (reading the scene's own would evaluate it, and the next
    solves' kernels, which had it as a literal, would change in the last bits).

    On CUDA (``method = "auto"``) Sionna's ``cfr`` sums instead: the frozen kernel loops over
    the paths one after the other in a lane per (receiver, antenna pair), a few hundred
    lanes, which a GPU runs poorly. On the H200 (2026-11-28) a warm solve of 1 UAV at 1e6
    samples took 112 ms with it against 69 ms with ``cfr`` the session before (not yet measured
    side by side; ``scripts/gpu_check.py`` does it on the next GPU run)."""
    dr, mi = jit()
    if method not in CARRIER_METHODS:
        raise ValueError(f"carrier method: expected one of {', '.join(CARRIER_METHODS)}, got {method!r}")
    if method == "cfr" or (method == "auto" and str(mi.variant()).startswith("cuda_")):
        cfr = paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")
        valid = np.array(paths.valid).reshape(n_rx, -1)  # [rx, paths] (one transmitter)
        tau = np.array(paths.tau).reshape(n_rx, -1)
        return cfr[:, :, 0, :, 0, 0].astype(np.complex64), valid, tau.astype(np.float32)
    a_re, a_im = paths.a
    n_paths = int(a_re.shape[-1])
    n_ant = int(np.prod(a_re.shape[1:4]))
    if n_paths == 0:
        empty = np.zeros((n_rx, 0))
        return (np.zeros((n_rx, a_re.shape[1], a_re.shape[3]), dtype=np.complex64), empty.astype(bool),
                empty.astype(np.float32))
    frozen = FROZEN.get("carrier")
    if frozen is None:
        frozen = FROZEN["carrier"] = dr.freeze(carrier_sums)
    args = (a_re.array, a_im.array, paths.tau.array, dr.opaque(mi.UInt, n_paths), dr.opaque(mi.UInt, n_ant),
            dr.opaque(mi.Float, float(np.float32(frequency_hz))), n_rx * n_ant)
    try:
        h_re, h_im = frozen(*args)
    except RuntimeError as e:  # (a backend where freezing fails: the same kernel, traced each time)
        warnings.warn(f"dr.freeze failed on the carrier channel ({e}); it is traced on every solve",
                      RuntimeWarning, stacklevel=2)
        FROZEN["carrier"] = carrier_sums
        h_re, h_im = carrier_sums(*args)
    dr.eval(h_re, h_im, paths.valid)
    tau = np.asarray(paths.tau).reshape(n_rx, -1)  # [rx, P] (one transmitter)
    valid = np.asarray(paths.valid).reshape(n_rx, -1)
    h = (np.asarray(h_re) + 1j * np.asarray(h_im)).astype(np.complex64)
    return h.reshape(n_rx, a_re.shape[1], a_re.shape[3]), valid, tau
