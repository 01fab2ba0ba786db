"""The identification methods, by the name the API, the CLI and the archive use.

Each :class:`Method` says what it needs: a lost-in-space method names its
hypothesis generator (a function of the prepared pattern, the sky and the
options that yields batches of :class:`app.identification.hypotheses.Hypotheses`
with their check tolerances and the pattern features used so far); tracking
needs a prior attitude instead (:mod:`app.identification.near_prior`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from app.identification.hypotheses import bright_pair_batches


def tf_batches(p, sky, options):
    """:func:`app.identification.triangle_features.tf_batches`, imported when first used: most
    processes never search by triangle features, and a start-up is measured in milliseconds."""
    from app.identification.triangle_features import tf_batches as batches

    return batches(p, sky, options)


@dataclass(frozen=True)
class Method:
    name: str
    description: str
    #: Lost-in-space hypothesis generator; None for tracking.
    hypotheses: Callable | None = None
    #: Tracking matches near a prior attitude instead of searching the sky.
    needs_prior: bool = False
    #: Its hypotheses come from the bright-pair index, so a match of the index's bright triangles
    #: (:mod:`app.identification.focal_estimate`) is one of its own; another method stays an independent
    #: opinion and uses them only to choose the focal length searched first.
    bright_triangles: bool = False
    #: Its other focal lengths are searched at once, each catalogue pair at its nearest
    #: (:mod:`app.identification.focal_scan`: bright pairs), not step by step.
    focal_scan: bool = False
    #: Why a pattern can give this method no feature at all, said when it gives none (an operator who sees
    #: "0 hypotheses from 0 pattern features" needs to know it is the method, not the sky).
    no_feature: str = ""


METHODS: dict[str, Method] = {m.name: m for m in (
    Method("bright_pair", "the seed's bright-pair index, edges looked up by length (lost in space; default)",
           hypotheses=bright_pair_batches, bright_triangles=True, focal_scan=True),
    Method("tf", "Liebe's triangle features: two angular distances and the spherical angle (lost in space)",
           hypotheses=tf_batches,
           no_feature="no pattern point has its two nearest neighbours nearer than the sensor's edge (Liebe's rim "
                      "rule for a triangle feature): the pattern is too sparse for this method; bright pairs need "
                      "no such neighbours"),
    Method("tracking", "match near a prior attitude (Liebe's predictional estimate; FUSE's known tracking)",
           needs_prior=True),
)}
