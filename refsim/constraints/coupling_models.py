"""The needle–tissue coupling a scene chooses (``insertion.coupling``), as an object chosen once when the
scene is loaded (:attr:`refsim.scene.spec.InsertionSpec.coupling_model`), holding its own parameters, the way
the cutting laws are (:mod:`refsim.cutting.laws`). Detection asks it whether the insertion rows average the
tissue over rings (and need the rest mesh to lay them); the events ask it how far past the tip a point must
lie before it is released. The rows themselves are built in :mod:`refsim.constraints.coupling` (the ring) and
:mod:`refsim.constraints.insertion` (the paper's line); docs/coupling.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

__all__ = ["COUPLING_MODELS", "Coupling", "PaperCoupling", "RingCoupling"]


@dataclass(frozen=True)
class Coupling:
    """A coupling: its scene name, whether its rows are laid on rings, and its release margin."""

    name: ClassVar[str] = ""
    #: Its insertion rows average the tissue over a ring of material points laid in the rest mesh.
    rings: ClassVar[bool] = False

    def retraction_margin(self, spacing: float) -> float:
        """How far beyond the tip [m] an insertion point must lie before the retraction removes it
        (``spacing``: d_i)."""
        return 0.0


@dataclass(frozen=True)
class RingCoupling(Coupling):
    """The well-posed coupling (default): rows on the mean displacement of a ring of radius max(r, h), with
    the annulus' sub-grid compliance (docs/coupling.md).

    Attributes
    ----------
    retraction_hysteresis : The release margin as a fraction of d_i. A ring point's centre is not tied to
        the needle (its ring is): it drifts along the needle with the tissue's strain, and half a spacing of
        hysteresis keeps that drift from removing a point and adding it back.
    """

    name: ClassVar[str] = "ring"
    rings: ClassVar[bool] = True
    retraction_hysteresis: float = 0.5

    def retraction_margin(self, spacing: float) -> float:
        return self.retraction_hysteresis * float(spacing)


@dataclass(frozen=True)
class PaperCoupling(Coupling):
    """The paper's coupling: two lateral rows and a shaft row on the centreline at each insertion point, tied
    to the needle (a point is released as soon as it lies beyond the tip)."""

    name: ClassVar[str] = "paper"


#: The couplings a scene may choose, by ``insertion.coupling``.
COUPLING_MODELS: dict[str, type[Coupling]] = {each.name: each for each in (RingCoupling, PaperCoupling)}
