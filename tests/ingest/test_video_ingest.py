"""Videos through the ingest stage: keyframes land in images/ under ordered names, ingest.json's ``videos``
block says what was taken and why, and bad videos (garbage, truncated, audio only, empty) are skipped with a
reason while the rest of the set ingests."""

from __future__ import annotations

import json
import zipfile
from datetime import UTC, datetime, timedelta
from pathlib import Path

import av
import numpy as np
import pytest
from video_fixtures import SEGMENTS, write_segment_video

from pipeline.ingest.intake import IngestError, ingest
from pipeline.ingest.video import VideoConfig, VideoError, extract_keyframes
from pipeline.job.layout import JobLayout
from pipeline.scene.images import read_image, write_image
from pipeline.sfm.recipe import is_numbered_sequence


def _jpegs(folder: Path, n: int) -> list[Path]:
    rng = np.random.default_rng(0)
    out = []
    for i in range(n):
        p = folder / f"photo_{i}.jpg"
        write_image(p, (rng.random((48, 64, 3)) * 255).astype(np.uint8))
        out.append(p)
    return out


def _audio_only(path: Path) -> Path:
    with av.open(str(path), "w") as out:
        stream = out.add_stream("aac", rate=8000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
        frame.sample_rate = 8000
        for _ in range(4):
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def _no_frames(path: Path) -> Path:
    """A container with a video stream header and no packet: FFmpeg reports no stream at all."""
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=10)
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        out.start_encoding()
        for packet in stream.encode():
            out.mux(packet)
    return path


def _faststart(clip: Path, dst: Path, creation_time: str | None = None) -> Path:
    """``clip`` remuxed with its index in front (moov before mdat), so a cut or damaged tail still opens."""
    with av.open(str(clip)) as inp, av.open(str(dst), "w", options={"movflags": "faststart"}) as out:
        if creation_time:
            out.metadata["creation_time"] = creation_time
        src = inp.streams.video[0]
        stream = out.add_stream_from_template(src)
        for packet in inp.demux(src):
            if packet.dts is not None:
                packet.stream = stream
                out.mux(packet)
    return dst


def _zeroed_data(clip: Path, dst: Path) -> Path:
    """A video whose index is intact and whose compressed frames are all zeros: no frame decodes."""
    data = _faststart(clip, dst).read_bytes()
    at = data.find(b"mdat") + 4
    dst.write_bytes(data[:at] + bytes(len(data) - at))
    return dst


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    return write_segment_video(tmp_path_factory.mktemp("clip") / "GOPR0042.MP4")[0]


def test_archive_with_a_video_and_bad_ones(tmp_path: Path, clip: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    photos = _jpegs(src, 2)
    data = clip.read_bytes()
    entries = {f"dive/{p.name}": p.read_bytes() for p in photos}
    entries["dive/GOPR0042.MP4"] = data
    entries["dive/garbage.mp4"] = b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40
    entries["dive/truncated.mov"] = data[: len(data) // 2]  # the moov atom (at the end) is gone
    entries["dive/sound.m4v"] = _audio_only(tmp_path / "sound.mp4").read_bytes()
    entries["dive/empty.mp4"] = _no_frames(tmp_path / "empty.mp4").read_bytes()
    entries["dive/zeros.mp4"] = _zeroed_data(clip, tmp_path / "zeros.mp4").read_bytes()
    entries["dive/notes.txt"] = b"transect 3"
    archive = tmp_path / "set.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for name, blob in entries.items():
            z.writestr(name, blob)
    job = tmp_path / "job"
    res = ingest(archive, job)

    kept = [n for n in res.images if n.startswith("dive__GOPR0042_")]
    assert 8 <= len(kept) <= 12 and len(res.images) == len(kept) + 2
    assert is_numbered_sequence(kept)  # SfM's rule for sequential matching holds for one video's frames
    first = read_image(JobLayout(job).images / kept[0])
    assert first.shape == (96, 128, 3)  # written at the video's size
    skipped = {s["file"]: s["reason"] for s in res.skipped}
    assert set(skipped) == {"dive/garbage.mp4", "dive/truncated.mov", "dive/sound.m4v", "dive/empty.mp4",
                            "dive/zeros.mp4"}
    assert "not a readable video" in skipped["dive/garbage.mp4"]
    assert "not a readable video" in skipped["dive/truncated.mov"]
    assert "no video stream (audio)" in skipped["dive/sound.m4v"]
    assert "no video stream (no streams)" in skipped["dive/empty.mp4"]
    assert "no frame could be decoded: decoding stopped after 0 frame(s)" in skipped["dive/zeros.mp4"]
    assert not any(str(job) in r or str(tmp_path) in r for r in skipped.values())  # no server paths
    assert [i["file"] for i in res.ignored] == ["dive/notes.txt"]

    block = json.loads(JobLayout(job).ingest.read_text())["videos"]
    assert [v["file"] for v in block] == ["dive/GOPR0042.MP4", "dive/empty.mp4", "dive/garbage.mp4",
                                          "dive/sound.m4v", "dive/truncated.mov", "dive/zeros.mp4"]
    good = block[0]
    assert good["frames_decoded"] == sum(n for _, n in SEGMENTS) and good["error"] is None
    assert [k["image"] for k in good["kept"]] == kept
    assert set(good["kept"][0]) == {"image", "index", "time", "capture_time", "sharpness", "overlap", "why"}
    assert good["kept"][0]["why"] == "first" and {k["why"] for k in good["kept"][1:]} <= {"overlap", "end"}
    assert good["rejected"]["blur"] >= 18 and sum(good["rejected"].values()) + len(kept) == good["frames_decoded"]
    assert {v["code"] for v in block[1:]} == {"unreadable_video", "no_video_stream", "no_frames"}


def test_only_a_bad_video_is_too_few_images(tmp_path: Path) -> None:
    src = tmp_path / "src"
    src.mkdir()
    (src / "broken.mp4").write_bytes(b"not a video at all" * 100)
    with pytest.raises(IngestError) as e:
        ingest(src, tmp_path / "job")
    assert e.value.code == "too_few_images" and "1 file(s) could not be decoded" in str(e.value)


def test_a_stream_cut_short_keeps_what_came_before(tmp_path: Path, clip: Path) -> None:
    """A video whose index sits in front (faststart) and whose data is cut: the frames before the cut are used."""
    whole = _faststart(clip, tmp_path / "fast.mp4")
    data = whole.read_bytes()
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    out_dir = tmp_path / "images"
    out_dir.mkdir()
    rep = extract_keyframes(cut, "cut.mp4", out_dir, "cut", {}, VideoConfig())
    assert 0 < rep.frames_decoded < sum(n for _, n in SEGMENTS)
    assert len(rep.kept) >= 2 and len(list(out_dir.iterdir())) == len(rep.kept)


def test_creation_time_gives_capture_times(tmp_path: Path, clip: Path) -> None:
    stamped = _faststart(clip, tmp_path / "stamped.mp4", "2026-03-01T10:00:00.000000Z")
    out_dir = tmp_path / "images"
    out_dir.mkdir()
    rep = extract_keyframes(stamped, "stamped.mp4", out_dir, "s", {}, VideoConfig(max_keyframes=2))
    assert rep.creation_time == "2026-03-01T10:00:00Z"
    start = datetime(2026, 3, 1, 10, tzinfo=UTC)
    for k in rep.kept:
        assert k["capture_time"] == (start + timedelta(seconds=k["time"])).isoformat().replace("+00:00", "Z")
    assert rep.kept[1]["time"] > 0


def test_unreadable_video_error_is_typed(tmp_path: Path) -> None:
    p = tmp_path / "x.mov"
    p.write_bytes(b"")
    with pytest.raises(VideoError) as e:
        extract_keyframes(p, "x.mov", tmp_path, "x", {}, VideoConfig())
    assert e.value.code == "unreadable_video" and str(tmp_path) not in str(e.value)


def test_a_phone_video_is_written_upright(tmp_path: Path) -> None:
    """A display matrix of 90° (counter-clockwise, as a phone held upright records): frames are rotated so."""
    rng = np.random.default_rng(0)
    frame = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
    frame[:8, :8] = 255  # a white corner, top left as stored
    p = tmp_path / "phone.mp4"
    with av.open(str(p), "w") as out:
        stream = out.add_stream("libx264", rate=10, options={"crf": "10"})
        stream.width, stream.height, stream.pix_fmt = 64, 48, "yuv420p"
        stream.set_display_rotation(90)
        for _ in range(3):
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    out_dir = tmp_path / "images"
    out_dir.mkdir()
    rep = extract_keyframes(p, "phone.mp4", out_dir, "phone", {}, VideoConfig())
    assert rep.rotation == 90 and rep.size == (64, 48)
    img = read_image(out_dir / rep.kept[0]["image"])
    assert img.shape[:2] == (64, 48)  # upright: portrait
    # counter-clockwise: the stored top-left corner is now bottom left
    assert img[-8:, :8].mean() > 0.9 and img[:8, :8].mean() < 0.8


def test_the_stage_reports_video_progress_and_stops_on_cancel(tmp_path: Path, clip: Path, monkeypatch) -> None:
    from pipeline.ingest import video as video_module
    from pipeline.ingest.stage import stage_ingest
    from pipeline.job.options import JobCancelled, JobOptions, StageContext

    monkeypatch.setattr(video_module, "TICK_FRAMES", 50)  # the clip has 130 frames
    src = tmp_path / "src"
    src.mkdir()
    (src / "clip.mp4").write_bytes(clip.read_bytes())
    seen: list[str] = []
    ctx = StageContext(on_progress=lambda stage, f, msg: seen.append(msg))
    res = stage_ingest(tmp_path / "job", JobOptions(source=str(src)), ctx)
    assert seen == ["video clip.mp4", "video clip.mp4: 50 frames", "video clip.mp4: 100 frames"]
    assert res["videos"][0]["frames_decoded"] == 130
    calls = iter([False, False, True])
    ctx = StageContext(should_cancel=lambda: next(calls))
    with pytest.raises(JobCancelled, match="clip.mp4: 100 frames"):
        stage_ingest(tmp_path / "job2", JobOptions(source=str(src)), ctx)


def test_one_video_is_a_whole_input(tmp_path: Path, clip: Path) -> None:
    """`dualphys run dive.mp4`: the video file itself is the source; its neighbours in the folder are not read."""
    (clip.parent / "other.jpg").write_bytes(b"not read")
    res = ingest(clip, tmp_path / "job")
    assert res.source == "GOPR0042.MP4" and len(res.images) == len(res.videos[0]["kept"]) >= 8
    assert all(n.startswith("GOPR0042_") for n in res.images) and not res.skipped and not res.ignored
