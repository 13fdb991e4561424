"""Track-guided recovery (issue 10): frames off the bone track searched again inside the
band the track allows.

Ground truth from the simulator (true contours per frame) on the hard preset, where the
per-frame step misses the faint top or offers the bone only in pieces.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import small_simulation

from BoneUSRecon.Logic.segmentation import (
    RecoveryParams,
    SegmentationParams,
    recover_frames,
    segment_sweep,
    select_bone_track,
)
from BoneUSRecon.Logic.segmentation.candidates import frame_candidates_many
from BoneUSRecon.Logic.segmentation.recovery import guided_candidate, track_prior
from BoneUSRecon.Logic.simulation.scoring import score_simulation

OFF = SegmentationParams(recovery=RecoveryParams(enabled=False))


def _hard(bone: str, seed: int = 7):
    return small_simulation(bone=bone, realism="hard", seed=seed)


def _recovered_medians(sim, after) -> list[float]:
    recovered = [c for c in after.accepted if c.extras.get("recovered")]
    assert after.summary()["recovered"] == len(recovered)
    return [float(np.median(sim.distance_to_truth(c.points_mm(sim.sweep)))) for c in recovered]


# Seeds where the first track misses many frames. Seed 7 (ulna, tibia) was used until
# the skin-gap shade rule (evidence._edge_gap): it puts ulna 7's frames 32-33 on the
# first track, leaving the 4 hardest to recovery (median 0.39 mm: the same contours as
# before, fewer easy ones), and it changes tibia 7's first track (see the xfail below).
# Tibia 29 was used until pieces over one shadow were joined (candidates._shadowed_span):
# its first track then holds 0.95 of the frames, leaving 2 to recovery.
@pytest.mark.parametrize(("bone", "seed"), [("ulna", 31), ("tibia", 7)])
def test_recovery_raises_recall_on_the_bone(bone, seed):
    """Hard sweeps: frames the per-frame step missed come back, every one on the bone."""
    sim = _hard(bone, seed)
    before = segment_sweep(sim.sweep, OFF)
    after = segment_sweep(sim.sweep)
    s0, s1 = score_simulation(before, sim), score_simulation(after, sim)
    # Measured: ulna 31 0.825 -> 1.00 (7 frames recovered), tibia 7 0.90 -> 1.00 (4).
    assert s1.recall >= s0.recall + 0.1
    assert s1.recall >= 0.95
    assert s1.wrong_share == 0.0
    medians = _recovered_medians(sim, after)
    assert len(medians) >= 3
    # Each on the bone (the recall criterion, mm); most within a few tenths (a frame
    # next to a track frame that is itself partly off inherits some of its error:
    # measured max 0.53 and 0.56 mm, medians 0.12 and 0.27 mm).
    assert max(medians) < 1.0
    assert np.median(medians) < 0.3
    # Frames on the first track keep their contours: recovery only adds.
    kept_before = {c.frame for c in before.accepted}
    assert kept_before <= {c.frame for c in after.accepted}


def test_recovered_frames_on_the_bone_beside_a_distant_track_frame():
    """Tibia seed 7 (0.3 mm, hard). Was a known failure until pieces over one shadow
    were joined (candidates._shadowed_span; recovered medians now 0.07-0.47 mm): the
    first track skipped frames 34-36 (track frames 33
    and 37; 37's contour is itself 0.62 mm off, partly on a layer). Frame 36's prior is
    frame 33's contour 17 mm away along the sweep over most columns, so the band is
    +-7.8 mm (one link tolerance, 1 + 0.4 x 17 mm) and the offset rule allows 3.9 mm:
    the guided path takes a layer running off the bone's shoulder ~2 mm above the
    faint left flank (evidence 0.6-1.5 against 0-1.2 on the flank), 1.59 mm off on
    median, and the track keeps it. Measured in main too on other sweeps (radius 13
    frame 27 1.39 mm, radius 31 frame 28 1.15 mm). Passes once recovery tells such a
    layer from the bone."""
    sim = _hard("tibia", 7)
    assert max(_recovered_medians(sim, segment_sweep(sim.sweep))) < 1.0


def test_recovery_off_is_the_plain_track():
    sim = _hard("ulna")
    r = segment_sweep(sim.sweep, OFF)
    assert r.summary()["recovered"] == 0
    assert not any(c.extras.get("recovered") for c in r.contours)


def _first_track(sim):
    sw = sim.sweep
    frames = frame_candidates_many(list(sw.frames), [sw.spacing_mm] * sw.n_frames)
    return frames, select_bone_track(frames, sw.image_to_reference)


def test_guided_candidate_follows_the_prior_onto_the_bone_only():
    """Inside the band around the track's neighbouring contours the bone is found to a
    fraction of a mm; the same prior moved 4 mm up into the soft tissue finds nothing
    (speckle holds no run of evidence over half the band), nor does a prior lying in
    the shadow under the bone."""
    sim = _hard("tibia")
    sw = sim.sweep
    frames, choice = _first_track(sim)
    on = np.flatnonzero(choice.chosen >= 0)
    # A frame on the track with track frames on both sides: its own choice left out.
    f = int(next(k for k in on[1:-1] if k - 1 in on and k + 1 in on))
    hidden = choice.chosen.copy()
    hidden[f] = -1
    masked = type(choice)(hidden, choice.confidence, choice.reason, choice.detail)
    prior = track_prior(frames, masked, sw.image_to_reference, f, 9)
    assert prior is not None and len(prior) == 2
    image = sw.frames[f]
    cand = guided_candidate(image, sw.spacing_mm, prior)
    assert cand is not None and cand.guided
    d = sim.distance_to_truth(sw.to_reference(f, cand.points_px))
    assert np.median(d) < 0.3  # mm
    for shift in (-4.0, 6.0):  # into the tissue above, into the shadow below (mm)
        moved = [(lat, depth + shift, z) for lat, depth, z in prior]
        assert guided_candidate(image, sw.spacing_mm, moved) is None, shift


def test_recover_frames_searches_only_between_track_frames():
    """Frames off the track are searched only with a track frame on each side (the ends
    of the track have one side to vouch for them); nothing is searched with recovery off."""
    sim = _hard("ulna")
    sw = sim.sweep
    frames, choice = _first_track(sim)
    on = np.flatnonzero(choice.chosen >= 0)
    calls: list[int] = []

    def image_of(n: int) -> np.ndarray:
        calls.append(n)
        return sw.frames[n]

    new, changed = recover_frames(frames, choice, sw.image_to_reference, image_of)
    assert changed and set(changed) <= set(calls)
    assert all(on[0] < n < on[-1] and choice.chosen[n] < 0 for n in calls)
    for n in changed:
        assert len(new[n].candidates) == len(frames[n].candidates) + 1
        assert new[n].candidates[-1].guided
    for n in set(range(len(frames))) - set(changed):
        assert new[n] is frames[n]
    calls.clear()
    same, none = recover_frames(
        frames, choice, sw.image_to_reference, image_of, params=RecoveryParams(enabled=False)
    )
    assert none == [] and calls == [] and all(a is b for a, b in zip(same, frames, strict=True))
