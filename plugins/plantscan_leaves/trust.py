"""How far each leaf's traits, and each plant's numbers, can be trusted.

Every leaf gets a **confidence** (0-1) and the **reasons** behind a low one; every plant
a **quality flag** ``ok`` / ``check`` / ``fail`` with its reasons.  The reasons are
measured conditions, each with its threshold and why (docs/leaves.md, "Trust"):

* ``phantom``: the phantom model puts ``PHANTOM_SHARE`` or more of the leaf's surface
  on phantom volume (hull the views could not carve; the true leaf lies somewhere in
  it), or its ``thick_share`` reaches the measurer's warning (``measure.in_phantom``);
* ``outline``: the perimeter is too short for the length (``measure.short_outline``: an
  outline runs base to tip and back, so one of the two is wrong);
* ``rejoined``: the leaf was joined from fragments with a merge the merge model was
  unsure of (probability under ``WEAK_MERGE``);
* ``small``: under ``SMALL_LEAF_UNITS2`` mesh units squared (a few voxels across: its
  outline and length are a few voxels' worth of hull);
* ``model``: a learned trust model (``plantscan_leaves.trust_model``, when the recipe's
  ``measure`` names one) gives the leaf a probability over 0.5 of being measured more than
  10 % off, merged, split or not a leaf; its confidence is the lower of the two;
* ``shape``: a leaf whose area is not what its length and width allow (area / (length x
  width) outside ``FILL_RANGE``: a flat leaf's planform fills 0.5-0.8 of its bounding
  rectangle, a grass blade 0.6-0.8, an ellipse pi/4).

The confidence is ``1 - max(penalty)`` over the reasons that hold (``PENALTY``), so a
leaf with any reason is below ``LOW_CONFIDENCE``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from plantscan_core.data import LeafTraits
from plantscan_leaves.measure import in_phantom, short_outline

LOW_CONFIDENCE = 0.5  # a leaf under this is "low confidence": its traits need a look
PHANTOM_SHARE = 0.25  # dev seeds: leaves measured >10 % off hold 25-60 %, good ones <= 15 %
WEAK_MERGE = 0.8  # a merge the model gives under 0.8: the join may be wrong
SMALL_LEAF_UNITS2 = 400.0  # one side, mesh units squared: 20 x 20 voxels
FILL_RANGE = (0.35, 0.95)  # area / (length x width) of a real leaf lies inside
PENALTY = {"phantom": 0.7, "outline": 0.7, "rejoined": 0.6, "small": 0.6, "shape": 0.6}
# plant flag
FAIL_LOW_SHARE = 0.5  # half the leaves low-confidence: the plant's leaf traits are not usable
DEBRIS_CHECK, DEBRIS_FAIL = 0.15, 0.5  # debris area over leaf area
FLAGS = ("ok", "check", "fail")


@dataclass
class Trust:
    """A confidence (0-1) and the reason codes behind it (empty: nothing known against)."""

    confidence: float
    reasons: list[str] = field(default_factory=list)
    model_why: list[str] = field(default_factory=list)  # the trust model's top features

    @property
    def low(self) -> bool:
        return self.confidence < LOW_CONFIDENCE


def leaf_trust(leaf: LeafTraits, evidence: dict[str, float] | None) -> Trust:
    """The trust of one measured leaf from its traits and the segmenter's ``evidence``."""
    ev = evidence or {}
    reasons = []
    if ev.get("phantom_share", 0.0) >= PHANTOM_SHARE or in_phantom(leaf):
        reasons.append("phantom")
    if short_outline(leaf):
        reasons.append("outline")
    if ev.get("fragments", 1) > 1 and ev.get("weakest_merge", 1.0) < WEAK_MERGE:
        reasons.append("rejoined")
    if "area_units2" in ev and ev["area_units2"] < SMALL_LEAF_UNITS2:
        reasons.append("small")
    box = leaf.length_mm * leaf.width_mm
    if box > 0 and not FILL_RANGE[0] <= leaf.area_mm2 / box <= FILL_RANGE[1]:
        reasons.append("shape")
    penalty = max((PENALTY[r] for r in reasons), default=0.0)
    return Trust(round(1.0 - penalty, 3), reasons)


REASON_TEXT = {
    "phantom": "lies partly on phantom volume (hull the views could not carve): more views "
               "or tilts carve it",
    "outline": "its perimeter is under 1.8x its length: the length ran into another organ or "
               "the outline broke",
    "rejoined": "joined from pieces with an uncertain merge",
    "small": "a few voxels across: a finer hull measures it",
    "shape": "its area does not fit its length and width",
}


def model_trust(rules: Trust, p_bad: float, why: list[str]) -> Trust:
    """The rules' trust with a trust model's (``plantscan_leaves.trust_model``): the lower
    confidence of the two; the reason ``model`` when the model's is under ``LOW_CONFIDENCE``
    (``why``: the features that raised its doubt most, for the message).  ``p_bad``: the
    model's doubt (``TrustModel.doubt``: its p_bad rescaled so its cut falls on 0.5)."""
    conf = round(1.0 - float(p_bad), 3)
    if conf >= LOW_CONFIDENCE:
        return Trust(min(rules.confidence, conf), rules.reasons)
    return Trust(min(rules.confidence, conf), [*rules.reasons, "model"], list(why))


def reason_text(reason: str, trust: Trust) -> str:
    """The words of one reason code of ``trust`` (``model`` names its features)."""
    if reason != "model":
        return REASON_TEXT[reason]
    from plantscan_leaves.trust_model import FEATURE_TEXT

    words = " and ".join(FEATURE_TEXT[f] for f in trust.model_why) or "its features together"
    return ("leaves like it on the virtual scanner's plants were measured more than 10 % off "
            f"(the trust model; mostly from {words})")


def plant_quality(trusts: list[Trust], debris_share: float, plant_views: int | None,
                  min_views: int, stem_share: float = 0.0,
                  max_stem_share: float = 0.0) -> tuple[str, list[str]]:
    """The plant's flag and its reasons (messages a scientist reads first).

    ``debris_share``: debris area over leaf area; ``plant_views``: views the hull was
    carved from (None: unknown); ``min_views``: what the family's recipe asks for (0:
    no check); ``stem_share``: the stem's share of the plant's surface, against
    ``max_stem_share``, the most the recipe's plants hold (0: no check): more flags the
    plant ``check``, twice as much ``fail`` (leaves labelled stem are missed leaves).
    """
    fail, check = [], []
    if not trusts:
        fail.append("no leaf found")
    low = sum(t.low for t in trusts)
    if trusts and low / len(trusts) >= FAIL_LOW_SHARE:
        fail.append(f"{low} of {len(trusts)} leaves have low confidence")
    elif low:
        check.append(f"{low} of {len(trusts)} leaves have low confidence")
    if debris_share >= DEBRIS_FAIL:
        fail.append(f"debris is {100 * debris_share:.0f} % of the leaf area")
    elif debris_share >= DEBRIS_CHECK:
        check.append(f"debris is {100 * debris_share:.0f} % of the leaf area")
    if max_stem_share and stem_share > max_stem_share:
        msg = (f"the stem holds {100 * stem_share:.0f} % of the plant's surface, more than the "
               f"{100 * max_stem_share:.0f} % of this recipe's plants: leaves labelled stem "
               "are missing from the leaf count and area, or phantom volume fused to it")
        (fail if stem_share > 2 * max_stem_share else check).append(msg)
    if min_views and plant_views is not None and plant_views < min_views:
        msg = (f"{plant_views} plant views, fewer than the {min_views} this recipe's plants "
               "need (phantom volume and merged leaves follow)")
        (fail if plant_views < min_views / 2 else check).append(msg)
    if fail:
        return "fail", fail + check
    return ("check", check) if check else ("ok", [])
