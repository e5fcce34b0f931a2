"""The job folder's layout: every path of a job folder is spelled in ``pipeline/job/layout.py`` and nowhere else
in the code that reads or writes job folders; ``JobLayout`` itself; job folders from before the classifier's
file was renamed."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from pipeline.job.layout import RENDER_FOLDERS, JobLayout
from pipeline.job.markers import atomic_write_json, marker_path, run_marked

REPO = Path(__file__).resolve().parents[2]
SCANNED = ("pipeline", "service", "worker", "bench")
LAYOUT_FILE = Path("pipeline/job/layout.py")

# The job folder's file names (the list, and what JobLayout adds: asserted to stay in it below).
FILE_NAMES = ("job.json", "ingest.json", "classify.json", "water.json", "latest.pt", "train.json", "selection.json",
              "recovery.json", "collapsed.pt", "evaluate.json", "reconstruction.ply", "reconstruction.spz",
              "cameras.json", "report.json", "report.html",
              "speed_vs_error.png", ".stages", ".artifacts.json", "manifest.json", "log.txt", "source.json",
              "restore.json", ".previews", "survey.json", "ortho.tif", "ortho_water.tif", "ortho_confidence.tif",
              "dem.tif", "ortho.jpg", "ortho_water.jpg", "dem_hillshade.png")
# Folders whose names are ordinary words elsewhere ("train" the stage, "input" a report key): spelled as a path
# (``x / "train"``, ``"train/..."``) they are the job folder's.
FOLDER_NAMES = ("train", "output", "evaluate", "input", "upload", "true_camera", "renders", "confidence", "survey",
                "records")
# ``images/`` and ``scene/`` are not checked: a generated scene and SfM's output folder have their own.
# Allowed outside layout.py: a generated scene's true water (a scene path: pipeline.synth.water.TRUE_WATER_FILE).
# A registered survey folder's own record (service.surveys, a folder of sets, not a job) is also "survey.json".
ALLOWED = {"water.json": {Path("pipeline/synth/water.py")}, "survey.json": {Path("service/surveys/registry.py")}}

_NAME_RES = {n: re.compile(rf"(?<![\w.-]){re.escape(n)}(?![\w-])") for n in FILE_NAMES}
_FOLDER_RE = re.compile(rf"(?:^|[\s(\"'`/])(?:{'|'.join(FOLDER_NAMES)})/")
_TRAIN_CONFIG_RE = re.compile(r"train/config\.json")


def _strings(tree: ast.AST) -> list[ast.Constant]:
    """String constants, f-strings' constant parts included, docstrings (bare string statements) excluded."""
    docs = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    return [n for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def offenders(root: Path = REPO, dirs: tuple[str, ...] = SCANNED) -> list[str]:
    """``file:line: 'constant' (name)`` for every job-folder path spelled outside ``pipeline/job/layout.py``."""
    out = []
    for d in dirs:
        for path in sorted((root / d).rglob("*.py")):
            rel = path.relative_to(root)
            if rel == LAYOUT_FILE or ".venv" in rel.parts:
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"), str(rel))
            for node in _strings(tree):
                s = node.value
                hits = [n for n, rx in _NAME_RES.items() if rx.search(s) and rel not in ALLOWED.get(n, ())]
                hits += ["<folder>/"] if _FOLDER_RE.search(s) else []
                hits += ["train/config.json"] if _TRAIN_CONFIG_RE.search(s) else []
                out += [f"{rel}:{node.lineno}: {s!r} ({', '.join(hits)})"] if hits else []
            for node in ast.walk(tree):  # x / "train", and x / "config.json" where x is the train folder
                if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)
                        and isinstance(node.right, ast.Constant) and isinstance(node.right.value, str)):
                    continue
                name = node.right.value
                if name in FOLDER_NAMES or (name == "config.json" and "train" in ast.unparse(node.left)):
                    out.append(f"{rel}:{node.lineno}: {ast.unparse(node)} (a job folder path)")
    return sorted(out, key=lambda s: (s.split(":")[0], int(s.split(":")[1])))


def test_job_folder_paths_are_spelled_only_in_the_layout():
    found = offenders()
    assert not found, ("job-folder paths spelled outside pipeline/job/layout.py (use JobLayout):\n  "
                       + "\n  ".join(found))


def test_the_scan_finds_a_reintroduced_literal(tmp_path):
    """The check above is not vacuous: each way of spelling a job path is caught, docstrings are not."""
    src = tmp_path / "pipeline" / "stage.py"
    src.parent.mkdir(parents=True)
    src.write_text('"""Writes job/classify.json and output/report.html (a docstring: allowed)."""\n'
                   'def f(job, name):\n'
                   '    """train/latest.pt too."""\n'
                   '    a = job / "water.json"\n'
                   '    b = job / "train" / name\n'
                   '    c = f"{job}/.stages/{name}.json"\n'
                   '    d = job.train / "config.json"\n'
                   '    e = f"kept (train/{name})"\n'
                   '    return a, b, c, d, e, "images", job / "scene"\n')
    found = offenders(tmp_path, ("pipeline",))
    assert [f.split(":")[1] for f in found] == ["4", "5", "6", "7", "8"], found
    assert "water.json" in found[0] and ".stages" in found[2] and "train/" in found[4]


def test_the_layout_spells_every_checked_name():
    """The names the scan looks for are the layout's (a renamed file gets checked under its new name)."""
    text = (REPO / LAYOUT_FILE).read_text()
    for name in FILE_NAMES + FOLDER_NAMES + ("config.json",):
        assert f'"{name}"' in text, name
    layout = JobLayout("/j")
    names = {p.name for p in _paths(layout).values()}
    assert names - {"j"} <= set(FILE_NAMES) | set(FOLDER_NAMES) | set(RENDER_FOLDERS) | {
        "config.json", "images", "scene", "archive", "x.json"}, names


def _paths(layout: JobLayout) -> dict[str, Path]:
    props = [k for k, v in vars(JobLayout).items() if isinstance(v, property) and k != "classify_written"]
    return {k: getattr(layout, k) for k in props} | {"marker": layout.marker("x"), "root": layout.root}


def test_job_layout_paths():
    j = JobLayout("/data/jobs/j1")
    rel = {k: j.relative(p) if p != j.root else "" for k, p in _paths(j).items()}
    assert rel == {
        "options": "job.json", "images": "images", "unpacked": "upload", "ingest": "ingest.json", "scene": "scene",
        "records": "records", "survey_result": "survey.json", "survey": "output/survey",
        "ortho": "output/survey/ortho.tif", "ortho_water": "output/survey/ortho_water.tif",
        "ortho_confidence": "output/survey/ortho_confidence.tif", "dem": "output/survey/dem.tif",
        "ortho_preview": "output/survey/ortho.jpg", "ortho_water_preview": "output/survey/ortho_water.jpg",
        "hillshade_preview": "output/survey/dem_hillshade.png",
        "classify": "classify.json", "legacy_classify": "water.json", "train": "train",
        "checkpoint": "train/latest.pt", "train_result": "train/train.json", "selection": "train/selection.json",
        "train_config": "train/config.json", "recovery": "train/recovery.json", "collapsed": "train/collapsed.pt",
        "evaluate": "evaluate.json", "evaluate_renders": "evaluate", "true_camera": "evaluate/true_camera",
        "output": "output", "ply": "output/reconstruction.ply", "spz": "output/reconstruction.spz",
        "cameras": "output/cameras.json", "report_json": "output/report.json",
        "report_html": "output/report.html", "curve_png": "output/speed_vs_error.png", "markers": ".stages",
        "renders": "output/renders", "restore_result": "restore.json", "restored": "output/restored",
        "confidence": "output/confidence", "previews": ".previews",
        "marker": ".stages/x.json", "manifest": "manifest.json", "log": "log.txt", "input": "input",
        "upload": "input/archive", "source_name": "source.json", "artifacts_cache": ".artifacts.json", "root": ""}
    assert JobLayout(Path("/data/jobs/j1")) == j and isinstance(j.root, Path)
    assert marker_path("/data/jobs/j1", "train") == j.marker("train")


def test_render_folders_are_the_known_ones():
    j = JobLayout("/j")
    assert [j.relative(j.render_folder(f)) for f in RENDER_FOLDERS] == [f"output/renders/{f}" for f in RENDER_FOLDERS]
    assert (j.relative(j.restored), j.relative(j.confidence)) == ("output/restored", "output/confidence")
    for bad in ("report.json", "../x", "", "Restored"):
        with pytest.raises(ValueError, match="unknown render folder"):
            j.render_folder(bad)


def test_the_classifier_decision_falls_back_to_the_legacy_file(tmp_path):
    j = JobLayout(tmp_path)
    assert j.classify_written is None  # not classified
    atomic_write_json(j.legacy_classify, {"water_type": "turbid"})
    assert j.classify_written == j.legacy_classify  # a job folder from before the rename
    atomic_write_json(j.classify, {"water_type": "clear"})
    assert j.classify_written == j.classify  # the classify stage ran again: its file wins


class _Stop(Exception):
    pass


def test_an_old_job_folder_resumes_training_with_its_water_decision(tmp_path, monkeypatch):
    """A job classified before the rename holds water.json and a classify marker that still matches: the stage
    is skipped on resume (classify.json never appears) and training must still get the decision."""
    import pipeline.train.guard as guard
    from pipeline.config import SynthConfig
    from pipeline.job.options import JobOptions, StageContext
    from pipeline.job.runner import run_stage, stage_config
    from pipeline.synth.procedural import generate_scene
    from pipeline.train.stage import stage_train

    job = JobLayout(tmp_path / "job")
    generate_scene(SynthConfig(views=8, width=64, height=48, preset="medium", seed=0), job.scene)
    opts = JobOptions(source=str(job.scene / "images"), mode="dualphys", iterations=10)
    decision = {"water_type": "turbid", "lr_attenuation": 1.25e-4, "lr_scattering": 3.5e-4, "alpha": 0.77,
                "beta": 1.33, "medium_start_fraction": 0.45}
    # what the classify stage left before the rename: its decision in water.json, its marker (same config hash)
    atomic_write_json(job.legacy_classify, decision)
    run_marked(job.root, "classify", stage_config(opts, "classify"), lambda: decision)
    assert run_stage(job.root, "classify", opts) == (decision, True)  # resumed: skipped, so ...
    assert not job.classify.exists()  # ... classify.json is never written

    seen: list = []

    def capture(scene, images, cfg, out, **kw):
        seen.append((cfg.medium, out))
        raise _Stop

    monkeypatch.setattr(guard, "train_checked", capture)
    with pytest.raises(_Stop):
        stage_train(job.root, opts, StageContext())
    medium, out = seen[-1]
    assert out == job.train
    assert (medium.lr_attenuation, medium.lr_scattering, medium.alpha_w, medium.beta_w, medium.start_fraction) == (
        1.25e-4, 3.5e-4, 0.77, 1.33, 0.45)

    job.legacy_classify.unlink()  # without the fallback the decision would be lost
    with pytest.raises(_Stop):
        stage_train(job.root, opts, StageContext())
    assert seen[-1][0].alpha_w != 0.77
