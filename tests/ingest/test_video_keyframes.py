"""Keyframe selection: motion by phase correlation, blur by relative sharpness, and a video whose still and
blurred segments must not flood the keyframes while its moving parts are covered at the target overlap."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from video_fixtures import (
    BLUR_PX,
    SEGMENTS,
    STEP,
    H,
    W,
    segment_frames,
    segment_of,
    texture,
    write_segment_video,
)

from pipeline.ingest.keyframes import (
    KeyframeConfig,
    KeyframeSelector,
    _Correlator,
    block_mean,
    overlap_of,
    sharpness,
)
from pipeline.ingest.video import VideoConfig, extract_keyframes
from pipeline.scene.images import read_image


def _grey(rgb: np.ndarray) -> np.ndarray:
    return rgb.astype(np.float32).mean(axis=2)


@pytest.mark.parametrize("dy, dx", [(0, 0), (3, 5), (-7, 20), (12, -40)])
def test_phase_correlation_finds_the_shift(dy: int, dx: int) -> None:
    tex = _grey(texture(3, 200, 300))
    a = tex[50:140, 60:220]
    b = tex[50 - dy:140 - dy, 60 - dx:220 - dx]  # b(x) = a(x - d)
    c = _Correlator(a.shape)
    got_dy, got_dx, peak = c.shift(c.spectrum(a), c.spectrum(b), a.shape)
    assert abs(got_dy - dy) < 0.15 and abs(got_dx - dx) < 0.15
    # the peak falls with the share of the frame that is not shared (1 = identical)
    assert peak > 0.9 * overlap_of(dy, dx, *a.shape) - 0.15
    if (dy, dx) == (0, 0):
        assert peak == pytest.approx(1.0, abs=1e-3)


def test_unrelated_frames_do_not_correlate() -> None:
    a, b = _grey(texture(1, 90, 160)), _grey(texture(2, 90, 160))
    c = _Correlator(a.shape)
    assert c.shift(c.spectrum(a), c.spectrum(b), a.shape)[2] < KeyframeConfig().min_peak


def test_sharpness_and_block_mean() -> None:
    assert sharpness(np.full((20, 30), 0.5)) == 0.0
    g = _grey(texture(4, 64, 96))
    blurred = (g + np.roll(g, 1, 1) + np.roll(g, 2, 1) + np.roll(g, 3, 1)) / 4
    assert sharpness(blurred) < 0.5 * sharpness(g)
    assert sharpness(3.0 * g + 7.0) == pytest.approx(sharpness(g), rel=1e-4)  # contrast and offset free
    assert block_mean(np.ones((90, 330)), 160).shape == (30, 110)  # k = 3: the smallest factor that fits
    with pytest.raises(ValueError, match="grey frame"):
        sharpness(np.zeros((2, 40)))


def test_config_refuses_nonsense() -> None:
    with pytest.raises(ValueError, match="target_overlap"):
        KeyframeConfig(target_overlap=1.2)
    with pytest.raises(ValueError, match="window"):
        KeyframeConfig(target_overlap=0.9, window=0.2)
    with pytest.raises(ValueError, match="VideoConfig"):
        VideoConfig(max_keyframes=0)


def test_a_cut_is_a_lost_track_keyframe() -> None:
    """Frames of one texture, then of an unrelated one: the first frame after the cut is kept at once."""
    sel = KeyframeSelector(KeyframeConfig(), fps=10)
    a, b = _grey(texture(5, 120, 400)), _grey(texture(6, 120, 400))
    kept = []
    for i in range(12):
        src, x = (a, 2 * i) if i < 6 else (b, 2 * i)
        offer = sel.offer(i, i / 10, src[10:106, x:x + 128])
        if offer.kept is not None:
            kept.append((offer.kept.index, offer.kept.why))
    assert kept[0] == (0, "first")
    assert kept[1] == (6, "lost_track")
    assert len(kept) == 2  # the frames after the cut overlap the new keyframe


def test_still_and_blurred_segments_do_not_flood_the_keyframes(tmp_path: Path) -> None:
    """Moving (40 frames, 3 px/frame) | still (30) | blurred while moving (20, 9 px motion blur) | moving (40),
    128x96 frames, H.264: keyframes come from the moving parts, at the target overlap."""
    video, xs = write_segment_video(tmp_path / "clip.mp4")
    out = tmp_path / "images"
    out.mkdir()
    taken: dict[str, str] = {}
    cfg = VideoConfig()
    rep = extract_keyframes(video, "clip.mp4", out, "clip", taken, cfg)
    assert rep.frames_decoded == sum(n for _, n in SEGMENTS) and rep.error is None and rep.codec == "h264"
    assert rep.fps == 10.0 and rep.size == (W, H)
    idx = [k["index"] for k in rep.kept]
    per_segment = [sum(segment_of(i) == s for i in idx) for s in range(len(SEGMENTS))]
    assert per_segment[1] <= 1, per_segment  # still
    assert per_segment[2] == 0, per_segment  # blurred
    assert rep.rejected["blur"] >= 18 and rep.rejected["still"] >= 25, rep.rejected
    # the moving parts: 117 px then 117 px of motion at a 30 % shift per keyframe (38 px) -> 3-4 keyframes each
    assert 3 <= per_segment[0] <= 5 and 3 <= per_segment[3] <= 5, per_segment
    target = cfg.keyframes.target_overlap
    for a, b, k in zip(idx, idx[1:], rep.kept[1:]):
        true_overlap = overlap_of(0, xs[b] - xs[a], H, W)
        across_blur = segment_of(a) < 2 < segment_of(b)  # no keyframe lies in the blurred segment (above)
        if not across_blur:
            # within one moving stretch: at the target, to within the window and a frame's step
            assert target - STEP / W - 0.02 <= true_overlap <= target + cfg.keyframes.window + 0.02, (a, b)
        else:  # across the blur: the first sharp frame after it, however far the camera went meanwhile
            assert b in (90, 91), (a, b)  # 91: the window before the blur held a frame, kept when 90 came
        # the measured overlap (recorded) agrees with the true one; across the blur less closely: phase
        # correlation reads the step into the centred 9 px box blur, and the step out of it, as ~2.5 px of motion
        # each (its transfer function changes sign), so that pair's overlap is up to ~5 px / 128 = 0.04 low
        assert k["overlap"] == pytest.approx(true_overlap, abs=0.05 if across_blur else 0.02), (a, b)
    assert sorted(taken) == [f"clip_{i:06d}.jpg" for i in idx]
    # each written image is the frame of its index (a held candidate, written frames later, is not overwritten
    # by the decoder): closest to that source frame, within the two codecs' loss
    frames = [f for _, f in segment_frames()]
    for i in idx:
        img = read_image(out / f"clip_{i:06d}.jpg")
        err = {j: float(np.abs(img - frames[j] / 255.0).mean()) for j in range(max(0, i - 2), min(len(frames), i + 3))}
        assert min(err, key=err.get) == i or (segment_of(i) == 1 and err[i] < 0.05), (i, err)
        assert err[i] < 0.05, (i, err)  # neighbours 3 px away differ by ~0.1
    assert all(k["time"] == pytest.approx(k["index"] / 10, abs=1e-6) for k in rep.kept)
    assert rep.kept[-1]["index"] >= sum(n for _, n in SEGMENTS) - 14  # the end is covered


def test_a_soft_video_is_not_emptied(tmp_path: Path) -> None:
    """Every frame blurred (the camera's focus, the water): judged against its own level, nothing is 'blur'."""
    video, _ = write_segment_video(tmp_path / "soft.mp4", segments=(("moving", 60),), soft_px=BLUR_PX)
    out = tmp_path / "images"
    out.mkdir()
    rep = extract_keyframes(video, "soft.mp4", out, "soft", {}, VideoConfig())
    assert rep.rejected["blur"] <= 2, rep.rejected
    assert 5 <= len(rep.kept) <= 7  # 177 px of motion at 38 px a keyframe, plus the first and the end


def test_caps_stop_decoding(tmp_path: Path) -> None:
    video, _ = write_segment_video(tmp_path / "clip.mp4")
    out = tmp_path / "images"
    out.mkdir()
    rep = extract_keyframes(video, "clip.mp4", out, "c", {}, VideoConfig(max_keyframes=2))
    assert len(rep.kept) == 2 and rep.stopped.startswith("max_keyframes") and rep.frames_decoded < 40
    rep = extract_keyframes(video, "clip.mp4", out, "d", {}, VideoConfig(max_frames=25))
    assert rep.frames_decoded == 25 and rep.stopped.startswith("max_frames")
    assert [k["why"] for k in rep.kept] == ["first", "overlap", "overlap"]  # no "end": the stream was not read out
