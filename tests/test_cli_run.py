"""`dualphys run`, `render` and `ablate` in-process through the CLI's main(): exit codes, messages, resuming."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from cli.main import main
from pipeline.config import SynthConfig, TrainConfig, from_dict
from pipeline.job.layout import JobLayout
from pipeline.synth.procedural import generate_scene
from pipeline.train.checkpoint import load_checkpoint


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    # 12 views 160x120: what SfM registers reliably; trained at 80x60 (--max-width 80)
    return generate_scene(SynthConfig(views=12, width=160, height=120, preset="medium", seed=0),
                          tmp_path_factory.mktemp("scene"))


def _last_json(text: str) -> dict:
    return json.loads(text.strip().splitlines()[-1])


@pytest.mark.slow
def test_demo_prints_real_numbers_and_where_the_report_is(tmp_path, capsys):
    """`make demo`'s command, short: what it prints must come from the job (a broken line breaks the demo)."""
    assert main(["demo", "--out", str(tmp_path / "demo"), "--iterations", "60"]) == 0
    out = capsys.readouterr().out
    report = re.search(r"report: (\S+report\.html)", out)
    assert report and Path(report.group(1)).is_file()
    restored = re.search(r"restored J against the true clean images \(held-out views\): PSNR ([\d.]+) dB", out)
    photos = re.search(r"the photos themselves: ([\d.]+) dB", out)
    assert restored and photos and 8.0 < float(restored.group(1)) < 40.0 and 8.0 < float(photos.group(1)) < 25.0
    seen = re.search(r"over the (\d+) % of pixels a training view saw: restored J ([\d.]+) dB", out)
    assert seen and 30 <= int(seen.group(1)) <= 100 and 8.0 < float(seen.group(2)) < 40.0
    photos = re.search(r"your photos de-watered \(restored/, full resolution\) against the truth \(held-out\): "
                       r"([\d.]+) dB \(the model's J render carried into the photos: ([\d.]+) dB; the photos "
                       r"themselves: ([\d.]+) dB\)", out)
    assert photos and 8.0 < float(photos.group(3)) < float(photos.group(1)) < 45.0
    beta = re.findall(r"([RGB]) ([\d.]+) \(true ([\d.]+)\)", out)
    assert [c for c, _, _ in beta] == ["R", "G", "B"] and all(float(b) > 0 for _, b, _ in beta)


@pytest.mark.slow
def test_run_then_rerun_skips_every_stage_then_render(scene, tmp_path, capsys):
    job = tmp_path / "job"
    argv = ["run", str(scene / "images"), "--out", str(job), "--mode", "homogeneous", "--colour-space", "srgb",
            "--iterations", "60", "--max-width", "80"]
    assert main(argv) == 0
    first = _last_json(capsys.readouterr().out)
    assert first["skipped"] == [] and first["mode"] == "homogeneous"
    layout = JobLayout(job)
    for f in (layout.ply, layout.report_json, layout.report_html):
        assert f.is_file(), f
    assert len(list(layout.render_folder("restored").glob("*.png"))) == 12
    # issue 14: the photos themselves, de-watered: same names and sizes as the inputs, one confidence map each
    from pipeline.scene.images import read_image

    names = sorted(p.name for p in (scene / "images").iterdir())
    assert sorted(p.name for p in layout.restored.iterdir()) == names
    assert read_image(layout.restored / names[0]).shape == read_image(scene / "images" / names[0]).shape
    assert len(list(layout.confidence.glob("*_surface.png"))) == 12 and len(list(layout.confidence.glob("*.png"))) == 24
    restore = json.loads(layout.restore_result.read_text())
    assert restore["restored"] == 12 and restore["not_restored"] == [] and restore["truth"]["test"]["n"] == 2
    # the resolved config is saved, and it is the one the model was trained with
    resolved = json.loads(layout.train_config.read_text())
    assert (resolved["mode"], resolved["iterations"], resolved["downscale"]) == ("homogeneous", 60, 2)
    assert from_dict(TrainConfig, load_checkpoint(layout.checkpoint)["config"]) == from_dict(TrainConfig, resolved)

    assert main(argv) == 0
    out = capsys.readouterr()
    again = _last_json(out.out)
    assert again["skipped"] == ["ingest", "sfm", "classify", "train", "evaluate", "restore", "survey", "export"]
    assert "skipped (already done)" in out.err  # the progress lines say so too

    rendered = tmp_path / "render"
    assert main(["render", str(job), "--out", str(rendered), "--views", "frame_0001,frame_0002.png",
                 "--what", "photos,restored,with_water,attenuation", "--orbit", "3"]) == 0
    summary = _last_json(capsys.readouterr().out)
    assert summary["views"] == 5 and summary["novel"] == 3
    for folder in ("restored", "with_water", "attenuation"):  # laid out as the job's output folder
        names = sorted(p.name for p in (rendered / "renders" / folder).glob("*.png"))
        assert names == ["frame_0001.png", "frame_0002.png", "novel_0000.png", "novel_0001.png", "novel_0002.png"]
    assert not (rendered / "renders" / "depth").exists()
    assert summary["photos"] == 2  # the two chosen views' photos, de-watered (novel cameras have none)
    assert (rendered / "restored" / "frame_0001.png").read_bytes() == (layout.restored / "frame_0001.png").read_bytes()

    assert main(["render", str(job), "--out", str(rendered), "--views", "nope"]) == 1
    assert "no view named nope" in capsys.readouterr().err


def test_run_and_render_errors_are_one_line_messages(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "job")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("dualphys run: ") and "does not exist" in err and "Traceback" not in err

    (tmp_path / "empty").mkdir()
    assert main(["run", str(tmp_path / "empty"), "--out", str(tmp_path / "job")]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("dualphys run: ingest failed:") and "at least 3" in err

    assert main(["render", str(tmp_path / "job"), "--out", str(tmp_path / "r")]) == 1
    assert "no trained model" in capsys.readouterr().err

    with pytest.raises(SystemExit) as e:  # a bad command line is argparse's exit 2
        main(["run", str(tmp_path), "--out", str(tmp_path / "job"), "--mode", "bogus"])
    assert e.value.code == 2
    with pytest.raises(SystemExit) as e:
        main(["run", str(tmp_path), "--out", str(tmp_path / "job"), "--iterations", "0"])
    assert e.value.code == 2


def test_ablate_prints_the_table_and_writes_json(tmp_path, capsys):
    out = tmp_path / "ablation"
    assert main(["ablate", "--out", str(out), "--iterations", "40", "--views", "8", "--size", "64x48",
                 "--only", "3DGS,Total,MSBs only,L_ab only"]) == 0
    printed = capsys.readouterr().out
    report = json.loads((out / "ablation.json").read_text())
    assert [r["name"] for r in report["rows"]] == ["3DGS", "Total", "MSBs only", "L_ab only"]
    for r in report["rows"]:
        assert r["psnr"] > 10 and r["restored_psnr"] > 5 and r["seconds"] > 0
        assert r["name"] in printed
    assert report["rows"][0]["restored_psnr"] < report["rows"][0]["psnr"]  # 3dgs restores nothing: J = I
    assert main(["ablate", "--out", str(out), "--only", "no such row"]) == 1


def test_progress_lines_without_tqdm():
    import io

    from pipeline.job.progress import StageProgress

    buf = io.StringIO()
    p = StageProgress(["ingest", "train"], stream=buf, use_tqdm=False, min_interval=3600)
    p("ingest", 0.0, "started")
    p("ingest", 1.0, "skipped (already done)")
    p("train", 0.0, "started")
    p("train", 0.5, "iteration 5/10")  # throttled: within min_interval of the last line
    p("train", 1.0, "iteration 10/10")
    p("train", 1.0, "done")  # the stage already reported its end
    lines = buf.getvalue().splitlines()
    assert lines == ["[1/2] ingest:   0.0% started", "[1/2] ingest: 100.0% skipped (already done)",
                     "[2/2] train:   0.0% started", "[2/2] train: 100.0% iteration 10/10"]
    assert p.skipped == ["ingest"]
