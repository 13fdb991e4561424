"""Track-guided recovery (issue 10): frames off the bone track searched again inside the
band the track allows.

Ground truth from the simulator (true contours per frame) on the hard preset, where the
per-frame step misses the faint top or offers the bone only in pieces.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CADAVER, FLAT_BARE, small_simulation

from BoneUSRecon.Logic.segmentation import (
    RecoveryParams,
    SegmentationParams,
    recover_frames,
    recovery,
    segment_sweep,
    select_bone_track,
)
from BoneUSRecon.Logic.segmentation.candidates import frame_candidates_many
from BoneUSRecon.Logic.segmentation.evidence import bone_evidence
from BoneUSRecon.Logic.segmentation.recovery import across_field, guided_candidate, track_prior
from BoneUSRecon.Logic.simulation.scoring import score_simulation
from BoneUSRecon.Logic.sweep import frame_planes, pixels_to_reference

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
# Tibia 29 was used until the gap, ends and shoulder rules were merged: together they put
# 3 more of its frames on the first track (recall 0.825 -> 0.900 before recovery), and
# the 4 left to recovery are the harder ones (0.07-0.37 mm, median 0.303 mm: no frame
# worse than before, the easy ones gone). Tibia 11 missed as many on its first track
# until session 29's series rules put all but one there (0.975 -> 1.00); tibia 24 leaves
# 6 to recovery, until session 34 (a grain at an apex no longer cuts a dome: 1 left);
# tibia 19 leaves 3 (0.925 -> 1.00).
@pytest.mark.parametrize(("bone", "seed"), [("ulna", 31), ("tibia", 19)])
def test_recovery_raises_recall_on_the_bone(bone, seed):
    """Hard sweeps: frames the per-frame step missed come back, every one on the bone."""
    sim = _hard(bone, seed)
    before = segment_sweep(sim.sweep, OFF)
    after = segment_sweep(sim.sweep)
    s0, s1 = score_simulation(before, sim), score_simulation(after, sim)
    # Measured: ulna 31 0.875 -> 1.00 (5 frames recovered), tibia 11 0.900 -> 1.00 (4);
    # 0.925 -> 1.00 (3) since flat ends are followed round the outline (rim.py): one
    # more frame is on the first track; 0.95 -> 1.00 (2) since the shadow's z-score is
    # centred on the tissue (evidence._shadow_scale): another. Session 29: ulna 31 0.85 ->
    # 1.00 (7 recovered, medians 0.05-0.50 mm), tibia 24 0.85 -> 1.00 (6, 0.06-0.51 mm).
    assert s1.recall >= s0.recall + 0.05
    assert s1.recall >= 0.95
    assert s1.wrong_share == 0.0
    medians = _recovered_medians(sim, after)
    assert len(medians) >= 2
    # Each on the bone (the recall criterion, mm); most within a few tenths (a frame
    # next to a track frame that is itself partly off inherits some of its error:
    # measured max 0.53 and 0.15 mm, medians 0.44 and 0.06 mm; ulna 31's was 0.15 mm
    # with the farther track frame's band, whose extra 0.02 mm let frame 24's left end
    # reach the flank under a layer that frame 23's contour hooks onto: 0.15 mm, 0.44
    # mm with the nearer frame's band).
    assert max(medians) < 1.0
    assert np.median(medians) < 0.5
    # Frames on the first track keep their contours: recovery only adds.
    kept_before = {c.frame for c in before.accepted}
    assert kept_before <= {c.frame for c in after.accepted}


# A guided contour on a layer over a faint top, with the band grown for the farther
# vouching frame. First seen on tibia seed 7 (0.3 mm, hard): the first track skipped
# frames 34-36 and frame 36's band was +-7.8 mm (1 + 0.4 x 17 mm); the guided path took
# a layer ~2 mm over the faint left flank (1.59 mm off on median). Since the gap, ends
# and shoulder rules, tibia 7's first track holds those frames; the weakness stayed on
# radius 13 (frame 27, track frames 2.4 and 2.9 mm away, recovered 1.39 mm off) and
# ulna 29 (frame 18, 2.1 and 5.7 mm away, 1.48 mm off). The band is now the nearer
# vouching frame's link tolerance where both sides cover a column. Radius 13 recovers no
# frame since session 29's series rules (its frames on the first track): radius 29, three
# recovered, stands in.
@pytest.mark.parametrize(("bone", "seed"), [("radius", 29), ("ulna", 29)])
def test_recovered_frames_on_the_bone_beside_a_distant_track_frame(bone, seed):
    sim = _hard(bone, seed)
    result = segment_sweep(sim.sweep)
    medians = _recovered_medians(sim, result)
    assert medians  # each sweep recovers frames (measured: 2 and 1)
    # Measured: max 0.69 mm (radius 13 frame 0, a one-sided search past the track's
    # start) and 0.12 mm; 1.39 and 1.48 mm with the farther frame's band.
    assert max(medians) < 1.0
    assert score_simulation(result, sim).recall == 1.0


@pytest.mark.parametrize(("bone", "seed", "frame"), [("radius", 13, 27), ("ulna", 29, 18)])
def test_guided_band_is_the_nearer_track_frames_tolerance(bone, seed, frame):
    """Between two track frames the farther one does not widen the band: the guided
    contour of a faint top stays on the bone (mm against the simulator's truth), and
    stays there when the farther frame is pushed 10 mm further along the sweep (its
    link tolerance would then be +-7 mm, wide enough for any layer over the bone)."""
    sim = _hard(bone, seed)
    sw = sim.sweep
    frames, choice = _first_track(sim)
    assert choice.chosen[frame] < 0  # the per-frame step offers no contour on the track
    prior = track_prior(frames, choice, sw.image_to_reference, frame, 9)
    assert prior is not None and len(prior) == 2
    nearer = min(z for _, _, z in prior)
    farther = [(lat, depth, z if z == nearer else z + 10.0) for lat, depth, z in prior]
    for p in (prior, farther):
        cand = guided_candidate(sw.frames[frame], sw.spacing_mm, p)
        assert cand is not None
        d = sim.distance_to_truth(sw.to_reference(frame, cand.points_px))
        # Measured 0.42 and 0.12 mm (1.39 and 1.48 mm with the farther frame's band).
        assert np.median(d) < 0.6, p is prior


def test_recovery_off_is_the_plain_track():
    sim = _hard("ulna")
    r = segment_sweep(sim.sweep, OFF)
    assert r.summary()["recovered"] == 0
    assert not any(c.extras.get("recovered") for c in r.contours)


def _first_track(sim):
    sw = sim.sweep
    # The per-frame step without settle.py and rim.py: these frames (radius 13 frame 27,
    # ulna 29 frame 18) had no contour on the first track then; settled, they have one,
    # and the guided band is what is measured here. The shadow gate flat from 1 on, as
    # before session 46 (rising on to 2 where the shadow is deep, radius 13 frame 27
    # has a contour on the first track).
    bare = FLAT_BARE
    frames = frame_candidates_many(list(sw.frames), [sw.spacing_mm] * sw.n_frames, bare)
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


def _grey(bone: str, seed: int):
    return small_simulation(bone=bone, seed=seed, realism="hard", hard_conditions=("grey_shadow",))


def test_guided_search_between_track_frames_finds_a_top_over_reverberation_bands():
    """Radius under the grey shadow, seed 71 (unseen; the lead's harness, session 26):
    in frames 2, 3, 6, 7, 14 and 37 the per-frame step offers only the first
    reverberation copy (2.2-2.4 mm under the top) and the far cortex, and the guided
    search found no run: over the dome the shadow windows hold the bands, the shadow
    z-score reads the tissue level and the score stays under ``null_z``. Searched again
    with the gate open from the tissue level on where both sides vouch and the frame's
    own score holds no run (:func:`.recovery.vouched_evidence`), they are recovered on
    the bone: recall 0.85 -> 1.00, no wrong frame (measured medians 0.02-0.03 mm).
    Since session 47 (a series' top followed past its copy's columns,
    ``candidates._extend_top``) frames 2 and 4 reach further down the bone's left flank,
    and the track takes frame 3's own candidate, whose left half lies on the first copy
    (median 1.19 mm, not wrong): recall 0.975, the other five recovered as before.
    Since session 48 (a series' top read at its echo's crest, and judged against the
    series' own troughs) frame 14's own candidate is that top, on the first track."""
    sim = _grey("radius", 71)
    result = segment_sweep(sim.sweep)
    score = score_simulation(result, sim)
    assert score.recall >= 0.95  # measured 0.975 (0.85 before the guided search)
    assert score.wrong_share == 0.0
    by_frame = {f.frame: f for f in score.frames}
    for k in (2, 6, 7, 14, 37):
        assert by_frame[k].on_bone, k
    # Frame 14 is on the first track with its own candidate, the shallowest (the top:
    # measured 0.03 mm; the other 1.8 mm under it).
    frames, choice = _first_track(sim)
    assert choice.chosen[14] >= 0
    own = frames[14].candidates[int(choice.chosen[14])].points_px
    assert np.median(sim.distance_to_truth(sim.sweep.to_reference(14, own))) < 0.3
    assert min(np.median(c.points_px[:, 1]) for c in frames[14].usable) >= np.median(own[:, 1])
    # Frame 37 alone: off the first track (its one candidate is the far cortex, 9.8 mm
    # under frame 36's top); the track's neighbours (36 and 38) vouch, and the guided
    # contour lies on the true top (measured 0.03 mm).
    assert choice.chosen[37] < 0
    prior = track_prior(frames, choice, sim.sweep.image_to_reference, 37, 9)
    assert prior is not None and len(prior) == 2
    cand = guided_candidate(sim.sweep.frames[37], sim.sweep.spacing_mm, prior)
    assert cand is not None
    d = sim.distance_to_truth(sim.sweep.to_reference(37, cand.points_px))
    assert np.median(d) < 0.3
    # The same prior 4 mm up, in the soft tissue, still finds nothing: the gate opens
    # at the tissue level, and speckle holds no run over half the band.
    moved = [(lat, depth - 4.0, z) for lat, depth, z in prior]
    assert guided_candidate(sim.sweep.frames[37], sim.sweep.spacing_mm, moved) is None


def _true_prior(sim, f: int) -> list:
    """A prior for frame ``f`` from the bone's true contours in frames ``f - 1`` and
    ``f + 1`` (a track on the bone there), in ``f``'s plane."""
    sw = sim.sweep
    o, ax, n = frame_planes(sw.image_to_reference[f][None])
    out = []
    for g in (f - 1, f + 1):
        ref = pixels_to_reference(sw.image_to_reference[g], sim.true_contours_px[g][::4])
        a = recovery._project(ref, o[0], ax[0], n[0])
        k = np.argsort(a[:, 0])
        out.append((a[k, 0], a[k, 1], float(np.median(a[:, 2]))))
    return out


def test_a_band_across_the_field_is_no_guided_contour(monkeypatch):
    """With the probe off the skin a frame holds only the lens's reverberation: equally
    spaced bands across the whole image (the simulator's contact loss). Guided by the
    bone in the frames on either side, the band search finds one of the bands at the
    bone's depth; its line runs on over the whole field at that depth, so it is no bone
    (``recovery.across_field``). A frame showing the bone, guided the same way, is found
    on it, and its contour is no such line. Hard ulna at the cadaver's geometry (475 x
    405 at 0.108 mm), seed 173, frame 30: kept 0.5-1.1 mm from where the bone would be
    in 4 of the 5 bones of that seed before the rule, in 1 after (the radius, whose
    guided contour steps down over three bands, the deeper two fading over half the
    field on one side)."""
    sim = small_simulation(
        bone="ulna", seed=173, realism="hard", corrupted_fraction=0.15, **CADAVER
    )
    sw = sim.sweep
    sp = sw.spacing_mm
    assert sim.corruption_kinds[30] == "contact_loss"
    assert not {27, 28, 29} & set(sim.corruption_kinds)
    assert guided_candidate(sw.frames[30], sp, _true_prior(sim, 30)) is None
    with monkeypatch.context() as m:
        m.setattr(recovery, "across_field", lambda *a: False)
        band = guided_candidate(sw.frames[30], sp, _true_prior(sim, 30))
    assert band is not None  # the rule is what drops it
    lo, hi = np.percentile(band.core_px[:, 1], (10.0, 90.0))
    assert (hi - lo) * sp[1] < 1.0  # level over the middle 80 % of its depths, mm
    bone = guided_candidate(sw.frames[28], sp, _true_prior(sim, 28))
    assert bone is not None
    assert np.median(sim.distance_to_truth(sw.to_reference(28, bone.points_px))) < 0.3  # mm
    ev = bone_evidence(sw.frames[28], sp)
    assert not across_field(bone.core_px, ev, sp)


def test_a_frame_with_the_probe_off_the_skin_is_not_searched() -> None:
    """Hard radius, 160 x 128, 20 % corrupted frames, seed 7: in frame 16 the probe is
    off the skin (lens reverberation over the noise floor). Between two track frames the
    search the track vouches for found a path through the noise at the bone's depth and
    the frame was kept; its tissue level is half the sweep's median frame's, and such a
    frame is no longer searched (``RecoveryParams.contact_level``). The frames showing
    the bone keep their contours."""
    sim = small_simulation(
        bone="radius", seed=7, realism="hard", n_frames=24, corrupted_fraction=0.2
    )
    assert sim.corruption_kinds[16] == "contact_loss"
    off = SegmentationParams(recovery=RecoveryParams(contact_level=0.0))
    without, with_rule = segment_sweep(sim.sweep, off), segment_sweep(sim.sweep)
    assert without.contours[16].accepted  # the premise: found in the noise
    assert not with_rule.contours[16].accepted
    fs = score_simulation(with_rule, sim)
    assert fs.wrong_share == 0.0
    assert fs.recall >= score_simulation(without, sim).recall
