"""Every use of Sionna SYS's private internals, and of PyTorch's that the link level makes, in one
place (:mod:`caviar_plugins.rt.sionna_adapter` holds Sionna RT's).

**Sionna SYS.** The radio network's link level grows its outer-loop link adaptation and
proportional-fair scheduler to more UEs and resets a UE's column: their state tensors
(``_offset``, ``_sinr_eff_db_last``, ``_rate_achieved_past``) have no public setter.

Its loop of several groups of slots (``groups_per_call``) runs the two blocks on state of its own
(:func:`loops_on`) and marks Sionna's blocks built (``_built``) before it.

**PyTorch.** The compiled link level raises dynamo's recompile limit
(:func:`allow_recompiles`), which has no public setter, and loops with ``torch._higher_order_ops.scan``.
"""

from __future__ import annotations

import functools
import math
import types
from typing import Any


def grow_link_adaptation(new: Any, old: Any, count: int) -> None:
    """Copies the state of the first ``count`` UEs of an ``OuterLoopLinkAdaptation``
    (``old``) into a larger one (``new``): its offsets and last effective SINRs."""
    new._offset[..., :count] = old._offset
    new._sinr_eff_db_last[..., :count] = old._sinr_eff_db_last


def grow_scheduler(new: Any, old: Any, count: int) -> None:
    """Copies the achieved-rate history of the first ``count`` UEs of a
    ``PFSchedulerSUMIMO`` (``old``) into a larger one (``new``)."""
    new._rate_achieved_past[..., :count] = old._rate_achieved_past


def reset_scheduler_history(pf: Any, ue: int, cell: int | None = None) -> None:
    """A fresh proportional-fair history for UE column ``ue`` (in ``cell``; None: every cell)."""
    if cell is None:
        pf._rate_achieved_past[..., ue] = 1.0
    else:
        pf._rate_achieved_past[..., cell, ue] = 1.0


def reset_link_adaptation(olla: Any, ue: int) -> None:
    """UE column ``ue`` of an ``OuterLoopLinkAdaptation`` starts again with no offset."""
    olla._offset[..., ue] = 0.0


def loop_state(olla: Any, pf: Any) -> tuple:
    """Copies of what the link loops keep between slots (an ``OuterLoopLinkAdaptation``'s
    offsets and last effective SINRs, a ``PFSchedulerSUMIMO``'s achieved-rate history), for
    :func:`keep_loop_state` (compiled, no copy is made: the values before the group's calls)."""
    return tuple(t.clone() for t in loop_tensors(olla, pf)[:3])


def copy_out_link_adaptation(olla: Any) -> None:
    """An ``OuterLoopLinkAdaptation``'s offsets and last effective SINRs as copies of their own:
    a call sets them to new tensors (a replayed CUDA graph's output memory, which its next replay
    overwrites); its achieved-rate history, the scheduler keeps in place."""
    olla._offset, olla._sinr_eff_db_last = olla._offset.clone(), olla._sinr_eff_db_last.clone()


def keep_loop_state(olla: Any, pf: Any, kept: tuple, went: Any) -> None:
    """Puts :func:`loop_state`'s ``kept`` back for the links that sat a group of slots out
    (``went`` [L] False, the blocks' first batch axis): their loops as if it had not run."""
    import torch

    offset, sinr_last, past = kept
    olla._offset = torch.where(went[:, None, None], olla._offset, offset)
    olla._sinr_eff_db_last = torch.where(went[:, None, None], olla._sinr_eff_db_last, sinr_last)
    pf._rate_achieved_past.copy_(torch.where(went[:, None, None, None], pf._rate_achieved_past, past))


def loop_tensors(olla: Any, pf: Any) -> tuple:
    """What the link loops keep between slots, as they are (no copies): an
    ``OuterLoopLinkAdaptation``'s offsets and last effective SINRs, a ``PFSchedulerSUMIMO``'s
    achieved-rate history and last PF metrics (kept for a reader, never read by the scheduler)."""
    return olla._offset, olla._sinr_eff_db_last, pf._rate_achieved_past, pf._pf_metric


def set_loop_tensors(olla: Any, pf: Any, tensors: tuple) -> None:
    """Gives ``olla`` and ``pf`` the state :func:`loop_tensors` reads (of :func:`loops_on`'s stand-ins)."""
    olla._offset, olla._sinr_eff_db_last, past, metric = tensors
    pf._rate_achieved_past.copy_(past)
    pf._pf_metric.copy_(metric)


def loops_on(olla: Any, pf: Any, tensors: tuple, pf_schedules: bool = True) -> tuple:
    """Stand-ins for ``olla`` and ``pf`` that run the blocks' own ``call`` on ``tensors``
    (:func:`loop_tensors`'s, not changed: the scheduler's history copied, its metrics new where it
    schedules, else copied) and keep what it leaves to themselves: what the body of a loop torch
    compiles once (:func:`torch_scan`, whose body may change no object from outside it) can call.
    Every other attribute is the block's; its inputs already in the block's dtypes, no conversion.
    Sub-blocks must be built (:func:`built`)."""
    import torch

    offset, sinr_last, past, metric = tensors
    metric = torch.empty_like(metric) if pf_schedules else metric.clone()  # (written in full where it schedules)
    return (_OnState(_block=olla, _offset=offset, _sinr_eff_db_last=sinr_last),
            _OnState(_block=pf, _rate_achieved_past=past.clone(), _pf_metric=metric))


class _OnState(types.SimpleNamespace):
    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["_block"], name)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return type(self.__dict__["_block"]).call(self, *args, **kwargs)


def built(*blocks: Any) -> None:
    """Marks Sionna blocks and their sub-blocks built where building does nothing (Sionna SYS's
    blocks): a block sets its flag at its first call, a change a loop's body may not make."""
    from sionna.phy import Block

    for module in (m for block in blocks for m in block.modules()):
        if isinstance(module, Block) and not module.built:
            if type(module).build is not Block.build:
                raise TypeError(f"{type(module).__name__} builds on its first call: call it once first")
            module._built = True


def past_recompile_limit(error: Exception) -> bool:
    """Whether ``error`` is dynamo's refusal to compile a ``fullgraph`` function past its limit of
    compiled entries (:func:`allow_recompiles`), where a function without it would run eager."""
    import torch

    return isinstance(error, torch._dynamo.exc.FailOnRecompileLimitHit)


def torch_scan() -> Any:
    """torch's loop operator, compiled once whatever its length (``torch._higher_order_ops.scan``,
    a prototype without a public name): ``scan(body, carry, xs)``."""
    from torch._higher_order_ops import scan

    return scan


def block_state(block: Any) -> dict[str, Any]:
    """Copies of every tensor a Sionna SYS block keeps between calls, whatever it names them:
    its tensor attributes and its buffers (a ``torch.nn.Module``'s, where the proportional-fair
    scheduler keeps its rate history: ``vars()`` does not show them)."""
    import torch

    tensors = {k: v for k, v in vars(block).items() if isinstance(v, torch.Tensor)}
    if isinstance(block, torch.nn.Module):
        tensors.update(dict(block.named_buffers(recurse=False)))
    return {k: v.clone() for k, v in tensors.items()}


def set_block_state(block: Any, state: dict[str, Any]) -> None:
    """Puts back :func:`block_state` into a block built with the same settings (a buffer is
    set through the module, as an attribute)."""
    for name, value in state.items():
        setattr(block, name, value.clone())


def allow_recompiles(torch: Any, at_least: int) -> None:
    """Lets ``torch.compile`` keep ``at_least`` compiled entries per function (torch's
    ``_dynamo.config.recompile_limit``, 8 by default; past it a function runs eager)."""
    config = torch._dynamo.config
    config.recompile_limit = max(config.recompile_limit, at_least)


def own_generator(device: Any, seed: int) -> Any:
    """A torch generator on ``device`` seeded as ``sionna.phy.config.seed = seed`` would seed
    Sionna's generator for that device (``seed`` plus the device's index among Sionna's
    devices), without setting Sionna's seed: a block's own random stream."""
    import torch
    from sionna.phy import config

    name = str(device)
    index = config.available_devices.index(name) if name in config.available_devices else 0
    generator = torch.Generator(device=name)
    generator.manual_seed((int(seed) + index) % 2**64)
    return generator


def phy_abstraction(device: Any, generator: Any) -> Any:
    """Sionna SYS's ``PHYAbstraction`` on ``device`` drawing its HARQ outcomes from ``generator``
    (its ``torch_rng``, which is Sionna's shared generator for the device otherwise). One class
    for every link level (:func:`_own_stream_class`): a class made per call (as until 2026-11-29)
    failed dynamo's type guard of every other link level's compiled entries, so each new link
    level compiled its group of slots again (about 20 s, and after 32 of them torch's limit of
    entries ran the rest eager)."""
    block = _own_stream_class()(device=str(device))
    block._own_generator = generator
    return block


@functools.cache
def _own_stream_class() -> Any:
    """The ``PHYAbstraction`` whose ``torch_rng`` is the block's own generator (made once, at
    first use: Sionna is imported late)."""
    import sionna.sys
    import torch

    class OwnStream(sionna.sys.PHYAbstraction):
        @property
        def torch_rng(self):
            return self._own_generator  # (read eager only: compiled code draws from the device's default)

        def get_idx_from_grid(self, val: Any, which: str) -> Any:
            """Sionna's, the same numbers, with the grid's length from its (min, max, delta) as
            numpy's ``arange`` makes it (``ceil((max - min) / delta)``) instead of ``len`` of the
            numpy grid itself: in a compiled group of slots that made both grids tensor inputs,
            converted and guarded at every call (dynamo's lookup 165 -> 91 µs a call at 21 cells ×
            1,000 UEs, 2-core AMD EPYC)."""
            if which not in ("snr", "cbs"):
                raise ValueError("which must be 'snr' or 'cbs'")
            lo, hi, delta = self._snr_db_interp_min_max_delta if which == "snr" else self._cbs_interp_min_max_delta
            len_grid = max(math.ceil((hi - lo) / delta), 0)
            val = torch.as_tensor(val, dtype=self.dtype, device=self.device)
            idx = torch.round((val - lo) / delta).to(torch.int32)
            return torch.clamp(idx, 0, len_grid - 1)

    return OwnStream
