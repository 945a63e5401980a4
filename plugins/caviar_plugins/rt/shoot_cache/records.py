"""The typed records the shoot cache's phases hand each other.

* :class:`RayState`: the rays of a bounce loop between two depths (where each goes, its
  specular-chain flag and hashes, whether it is alive, the interactions still enabled);
* :class:`Interaction`: what one depth of the loop found for each ray
  (:func:`~caviar_plugins.rt.shoot_cache.shoot.interact`);
* :class:`DepthRecord`: the rays alive at one depth, as the connect phase reads them (hit
  points and normals, chains grouped by hash, the diffuse rays), and, for moving objects,
  where each goes next;
* :class:`Shots`: the shoot phase's result, a record per depth and the sample data the
  path buffer copies.

Fields holding Dr.Jit arrays are typed ``Any`` (their types come from the active Mitsuba
variant); the others are numpy.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from caviar_plugins.rt.drjit_setup import jit


def _none() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


@dataclasses.dataclass
class RayState:
    """The rays of a bounce loop before a depth (Sionna's loop state, without the targets)."""

    ray: Any
    """``mi.Ray3f``: where each ray sets off and its direction."""
    specular_chain: Any
    """``mi.Bool``: whether the ray's interactions so far form a specular chain."""
    hashes: list[Any]
    """Two ``mi.UInt64`` chain hashes (Sionna's round and floor hashers)."""
    active: Any
    """``mi.Mask``: rays still alive."""
    loc_en_inter: Any
    """``mi.UInt``: the interaction types still enabled for each ray (flags)."""
    touched: Any = None
    """``mi.Bool``, the one-loop bounce only: whether the ray has met a moving object yet
    (it is recorded from then on)."""


@dataclasses.dataclass
class Interaction:
    """One depth of the bounce loop for every ray (:func:`~caviar_plugins.rt.shoot_cache.shoot.interact`)."""

    si: Any
    """``mi.SurfaceInteraction3f``: the hits."""
    normal: Any
    """The normals oriented toward the incident side."""
    wedges: Any
    """The wedges sampled for diffraction."""
    k_world: Any
    """The outgoing direction of each ray."""
    active: Any
    """The rays that interacted."""
    loc_en_inter: Any
    specular_chain: Any
    hashes: list[Any]
    diffuse: Any
    diffraction: Any
    fields: Any
    """``SampleData.SampleDataFields`` of this depth (zeros for dead rays)."""


@dataclasses.dataclass
class DepthRecord:
    """The rays alive at one depth of the recorded bounces, as the connect phase reads them."""

    lane: Any
    """``mi.UInt``: each recorded ray's lane (index among the shots' rays), ascending."""
    p: Any = None
    """``mi.Point3f``: hit points."""
    n: Any = None
    """``mi.Normal3f``: normals oriented toward the incident side."""
    lanes: np.ndarray = dataclasses.field(default_factory=_none)
    """``lane`` as numpy (int64)."""
    grouped: np.ndarray = dataclasses.field(default_factory=_none)
    """The specular-chain rays (indices into this record), grouped by first hash, in ray
    order within a group."""
    starts: np.ndarray = dataclasses.field(default_factory=_none)
    """Where each group begins in ``grouped``."""
    sizes: np.ndarray = dataclasses.field(default_factory=_none)
    """Each group's ray count."""
    diffuse_rays: np.ndarray = dataclasses.field(default_factory=_none)
    """The rays (indices into this record) whose interaction here is diffuse."""
    h0: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.uint64))
    """Each ray's first chain hash."""
    h1: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.uint64))
    """Each ray's second chain hash."""
    o: Any = None
    """With moving objects only: where each ray sets off for its next segment (``mi.Point3f``)."""
    d: Any = None
    """... its direction (``mi.Vector3f``)."""
    chain_next: Any = None
    """... its specular-chain flag then (``mi.Bool``)."""
    loc: Any = None
    """... and the interactions still enabled (``mi.UInt``)."""

    @property
    def size(self) -> int:
        """Rays recorded at this depth."""
        return len(self.lanes)

    @property
    def goes_on(self) -> bool:
        """Whether the record keeps where its rays go next (moving objects)."""
        return self.o is not None

    @classmethod
    def empty(cls) -> DepthRecord:
        """A depth at which nothing was recorded (the aimed rays before any met a moving object)."""
        _, mi = jit()
        return cls(lane=mi.UInt())

    @classmethod
    def of(cls, lane, p, n, diffuse, specular_chain, hashes, ahead: tuple | None = None) -> DepthRecord:
        """The record of the rays ``lane`` (evaluated Dr.Jit arrays): their chains grouped by
        first hash in ray order, their diffuse rays listed (numpy). ``ahead``: (o, d,
        chain_next, loc) of each ray's next segment."""
        h0 = np.asarray(hashes[0]).astype(np.uint64)
        chain = np.flatnonzero(np.asarray(specular_chain, dtype=bool))
        grouped = chain[np.argsort(h0[chain], kind="stable")]
        hs = h0[grouped]
        starts = np.flatnonzero(np.r_[True, hs[1:] != hs[:-1]]) if len(hs) else _none()
        o, d, chain_next, loc = ahead if ahead is not None else (None,) * 4
        return cls(lane=lane, p=p, n=n, lanes=np.asarray(lane, dtype=np.int64), grouped=grouped, starts=starts,
                   sizes=np.diff(np.r_[starts, len(grouped)]),
                   diffuse_rays=np.flatnonzero(np.asarray(diffuse, dtype=bool)), h0=h0,
                   h1=np.asarray(hashes[1]).astype(np.uint64), o=o, d=d, chain_next=chain_next, loc=loc)


@dataclasses.dataclass
class Shots:
    """What the shoot phase keeps: per depth, the rays alive there and what the connect
    phase needs of them; over all depths, the sample data the path buffer copies."""

    width: int = 0
    """Rays (lanes)."""
    depths: list[DepthRecord] = dataclasses.field(default_factory=list)
    samples: Any = None
    """``SampleDataFields`` of every ray at every depth (zeros where dead), depth-major."""
    wedges: Any = None
    """The diffracting wedge of every ray (first order only); None without diffraction."""
    diffraction_depth: Any = None
    """The depth of that diffraction, 0 if none (``mi.UInt``)."""
    src_indices: Any = None
    """Each ray's source."""
    k_tx: Any = None
    """Each ray's direction of departure (``mi.Vector3f``)."""
    keeps_state: bool = False
    """Whether each depth keeps where its rays go next (moving objects)."""
