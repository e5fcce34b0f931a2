"""Ingest and safe archive extraction: every hostile or broken upload gets its typed refusal, nothing escapes."""

from __future__ import annotations

import io
import json
import os
import stat
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pipeline.ingest.archive import ArchiveError, ArchiveLimits, extract_archive
from pipeline.ingest.intake import IngestConfig, IngestError, ingest
from pipeline.job.layout import JobLayout
from pipeline.scene.images import read_image, write_image

REPO = Path(__file__).resolve().parents[2]
RUIE = REPO.parent / "shared" / "data" / "real" / "ruie-A188-A206" / "images"


def _jpeg_bytes(seed: int, tmp: Path) -> bytes:
    rng = np.random.default_rng(seed)
    p = tmp / f"src_{seed}.jpg"
    write_image(p, (rng.random((24, 32, 3)) * 255).astype(np.uint8))
    return p.read_bytes()


def _zip(path: Path, entries: dict[str, bytes], method=zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, "w", method) as z:
        for name, data in entries.items():
            z.writestr(name, data)
    return path


def _outside_files(root: Path, before: set[str]) -> set[str]:
    return {str(p) for p in root.rglob("*")} - before


@pytest.fixture()
def good(tmp_path: Path) -> dict[str, bytes]:
    return {f"dive/img_{i}.jpg": _jpeg_bytes(i, tmp_path) for i in range(4)}


def test_good_zip_and_tar_ingest(tmp_path: Path, good) -> None:
    z = _zip(tmp_path / "set.zip", {**good, "notes.txt": b"hello", ".DS_Store": b"x"})
    res = ingest(z, tmp_path / "job", IngestConfig())
    assert res.images == [f"dive__img_{i}.jpg" for i in range(4)]
    assert {i["file"] for i in res.ignored} == {"notes.txt", ".DS_Store"}
    assert not JobLayout(tmp_path / "job").unpacked.exists()
    for name, data in good.items():  # JPEGs in display orientation are copied byte for byte
        assert (JobLayout(tmp_path / "job").images / name.replace("/", "__")).read_bytes() == data

    t = tmp_path / "set.tar.gz"
    with tarfile.open(t, "w:gz") as tf:
        for name, data in good.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    assert len(ingest(t, tmp_path / "job2").images) == 4


@pytest.mark.parametrize(
    "case, code",
    [
        ("zip_slip", "path_escape"),
        ("absolute", "absolute_path"),
        ("zip_symlink", "link"),
        ("tar_symlink", "link"),
        ("tar_hardlink", "link"),
        ("tar_device", "special_file"),
        ("zip_bomb", "compression_bomb"),
        ("too_many", "too_many_entries"),
        ("too_big", "too_large"),
        ("not_archive", "not_an_archive"),
        ("truncated", "corrupt_archive"),
        ("nested", "nested_archive"),
        ("duplicate", "duplicate_name"),
        ("windows_slip", "path_escape"),
    ],
)
def test_hostile_archives_are_refused_and_leave_nothing(tmp_path: Path, good, case: str, code: str) -> None:
    a = tmp_path / "upload.bin"
    limits = ArchiveLimits()
    if case == "zip_slip":
        _zip(a, {**good, "../../evil.jpg": b"x"})
    elif case == "windows_slip":
        _zip(a, {**good, "..\\..\\evil.jpg": b"x"})
    elif case == "absolute":
        _zip(a, {**good, "/etc/evil.jpg": b"x"})
    elif case == "zip_symlink":
        with zipfile.ZipFile(a, "w") as z:
            for n, d in good.items():
                z.writestr(n, d)
            info = zipfile.ZipInfo("link.jpg")
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            z.writestr(info, "/etc/passwd")
    elif case in ("tar_symlink", "tar_hardlink", "tar_device"):
        with tarfile.open(a, "w") as tf:
            info = tarfile.TarInfo("x.jpg")
            info.type = {"tar_symlink": tarfile.SYMTYPE, "tar_hardlink": tarfile.LNKTYPE,
                         "tar_device": tarfile.CHRTYPE}[case]
            info.linkname = "/etc/passwd"
            tf.addfile(info)
    elif case == "zip_bomb":
        _zip(a, {**good, "zeros.jpg": b"\0" * (20 << 20)}, zipfile.ZIP_DEFLATED)
    elif case == "too_many":
        _zip(a, {f"f{i}.jpg": b"x" for i in range(30)})
        limits = ArchiveLimits(max_entries=20)
    elif case == "too_big":
        _zip(a, good)
        limits = ArchiveLimits(max_total_bytes=sum(len(d) for d in good.values()) - 1)
    elif case == "not_archive":
        a.write_bytes(b"this is not an archive at all" * 100)
    elif case == "truncated":
        _zip(tmp_path / "full.zip", good)
        data = (tmp_path / "full.zip").read_bytes()
        a.write_bytes(data[: len(data) * 2 // 3] + data[-22:])  # central directory kept, members cut
    elif case == "nested":
        _zip(a, {**good, "more/inner.zip": b"PK\x03\x04"})
    elif case == "duplicate":
        _zip(a, {**good, "A.jpg": b"x", "a.JPG": b"y"})
    before = {str(p) for p in tmp_path.rglob("*")}
    job = tmp_path / "job"
    with pytest.raises((ArchiveError, IngestError)) as exc:
        ingest(a, job, IngestConfig(limits=limits))
    assert exc.value.code == code, str(exc.value)
    created = _outside_files(tmp_path, before)
    assert not any("evil" in p or p.startswith("/etc") for p in created)
    unpacked = JobLayout(job).unpacked
    assert not unpacked.exists() or not any(unpacked.iterdir())
    assert not any(job.rglob("*.jpg")) if job.exists() else True


def test_corrupt_image_among_good_is_skipped_and_listed(tmp_path: Path, good) -> None:
    bad = good["dive/img_0.jpg"][:200]  # truncated JPEG
    z = _zip(tmp_path / "s.zip", {**good, "dive/broken.jpg": bad, "dive/garbage.jpg": os.urandom(500)})
    res = ingest(z, tmp_path / "job")
    assert len(res.images) == 4
    assert {s["file"] for s in res.skipped} == {"dive/broken.jpg", "dive/garbage.jpg"}
    assert all(s["reason"] for s in res.skipped)


@pytest.mark.parametrize("n_images", [0, 1, 2])
def test_too_few_images_is_refused_with_the_count(tmp_path: Path, good, n_images: int) -> None:
    entries = dict(list(good.items())[:n_images]) | {"readme.txt": b"notes"}
    with pytest.raises(IngestError) as exc:
        ingest(_zip(tmp_path / "s.zip", entries), tmp_path / "job")
    assert exc.value.code == "too_few_images" and f"{n_images} usable" in str(exc.value)


def test_unicode_names_and_misnamed_files_are_normalised(tmp_path: Path, good) -> None:
    data = list(good.values())
    z = _zip(tmp_path / "s.zip", {"récif/été 1.jpg": data[0], "récif/été 2.jpg": data[1], "ok/x.png": data[2]})
    res = ingest(z, tmp_path / "job")
    assert res.images == ["ok__x.jpg", "récif__été_1.jpg", "récif__été_2.jpg"]  # the JPEG named .png is a .jpg
    img = read_image(JobLayout(tmp_path / "job").images / "ok__x.jpg")
    assert img.shape == (24, 32, 3)


def test_exif_rotated_image_is_written_upright(tmp_path: Path) -> None:
    import OpenImageIO as oiio

    src = tmp_path / "src"
    src.mkdir()
    px = (np.random.default_rng(0).random((20, 30, 3)) * 255).astype(np.uint8)
    for i in range(3):
        spec = oiio.ImageSpec(30, 20, 3, "uint8")
        spec.attribute("Orientation", 6)
        out = oiio.ImageOutput.create(str(src / f"r{i}.jpg"))
        out.open(str(src / f"r{i}.jpg"), spec)
        out.write_image(px)
        out.close()
    res = ingest(src, tmp_path / "job")
    assert res.images == ["r0.png", "r1.png", "r2.png"]
    assert read_image(JobLayout(tmp_path / "job").images / "r0.png").shape == (30, 20, 3)


def test_real_survey_folder(tmp_path: Path) -> None:
    res = ingest(RUIE, tmp_path / "job")
    assert len(res.images) == 19 and not res.skipped


def test_extraction_into_nonempty_target_is_refused(tmp_path: Path, good) -> None:
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "keep").write_text("x")
    with pytest.raises(ValueError):
        extract_archive(_zip(tmp_path / "s.zip", good), tmp_path / "t")
    assert (tmp_path / "t" / "keep").read_text() == "x"


# ---------------------------------------------------------------- issue 13: ordinary tars, encrypted zips, names


def _tar_of_folder(path: Path, folder: Path, mode: str = "w:gz") -> Path:
    """What `tar czf x.tar.gz -C folder .` writes: a '.' member, then './'-prefixed names."""
    with tarfile.open(path, mode) as tf:
        tf.add(folder, arcname=".")
    return path


def test_dot_slash_tar_of_a_folder_is_accepted(tmp_path: Path, good) -> None:
    folder = tmp_path / "images"
    for name, data in good.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    t = _tar_of_folder(tmp_path / "x.tar.gz", folder)
    with tarfile.open(t) as tf:
        assert tf.getnames()[0] == "." and all(n == "." or n.startswith("./") for n in tf.getnames())
    res = ingest(t, tmp_path / "job")
    assert res.images == [f"dive__img_{i}.jpg" for i in range(4)]
    # the same archive from GNU tar itself, when it is installed
    import shutil
    import subprocess

    if shutil.which("tar"):
        t2 = tmp_path / "gnu.tar.gz"
        subprocess.run(["tar", "czf", str(t2), "-C", str(folder), "."], check=True)
        assert ingest(t2, tmp_path / "job-gnu").images == res.images


@pytest.mark.parametrize("name, code", [("./../evil.jpg", "path_escape"), ("./dive/../../evil.jpg", "path_escape"),
                                        ("./", "bad_name"), ("/./evil.jpg", "absolute_path")])
def test_dot_slash_does_not_open_escapes(tmp_path: Path, good, name: str, code: str) -> None:
    t = tmp_path / "x.tar"
    with tarfile.open(t, "w") as tf:
        for n, data in {**good, name: b"x"}.items():
            info = tarfile.TarInfo(n)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))  # a regular file named './' has an empty name: refused
    with pytest.raises(ArchiveError) as exc:
        ingest(t, tmp_path / "job")
    assert exc.value.code == code
    assert not (tmp_path / "evil.jpg").exists() and not (tmp_path.parent / "evil.jpg").exists()


def _encrypted_flag(path: Path) -> Path:
    """Mark every entry of a stored zip as encrypted (general purpose bit 0, local and central headers): zipfile
    then refuses to read it exactly as it refuses a `zip -P` archive (the live suite uses real ZipCrypto)."""
    data = bytearray(path.read_bytes())
    for sig, flag_at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):
        i = data.find(sig)
        while i >= 0:
            data[i + flag_at] |= 0x1
            i = data.find(sig, i + 4)
    path.write_bytes(bytes(data))
    return path


def test_encrypted_zip_is_a_typed_refusal(tmp_path: Path, good) -> None:
    z = _encrypted_flag(_zip(tmp_path / "enc.zip", good))
    with zipfile.ZipFile(z) as zf, pytest.raises(RuntimeError, match="encrypted"):
        zf.read("dive/img_0.jpg")  # what used to escape as a 500
    with pytest.raises(ArchiveError) as exc:
        ingest(z, tmp_path / "job")
    assert exc.value.code == "encrypted_archive" and "password" in str(exc.value)
    assert not JobLayout(tmp_path / "job").unpacked.exists()


@pytest.mark.parametrize("name", ["a" * 300 + ".jpg", "/".join(["d" * 200] * 6) + "/x.jpg"])
def test_over_long_member_name_is_refused_without_server_paths(tmp_path: Path, good, name: str) -> None:
    z = _zip(tmp_path / "long.zip", {**good, name: good["dive/img_0.jpg"]})
    with pytest.raises(ArchiveError) as exc:
        ingest(z, tmp_path / "job")
    assert exc.value.code == "name_too_long"
    assert str(tmp_path) not in str(exc.value) and len(str(exc.value)) < 400


def test_ingest_json_names_the_input_relative_to_the_job(tmp_path: Path, good) -> None:
    job = JobLayout(tmp_path / "job")
    job.input.mkdir(parents=True)
    z = _zip(job.upload, {**good, "dive/broken.jpg": good["dive/img_0.jpg"][:150]})
    res = ingest(z, job.root)
    written = json.loads(job.ingest.read_text())
    assert res.source == written["source"] == job.relative(job.upload) == "input/archive"  # the API's contract
    assert [s["file"] for s in res.skipped] == ["dive/broken.jpg"]
    assert str(tmp_path) not in job.ingest.read_text()
    outside = _zip(tmp_path / "set.zip", good)
    assert ingest(outside, tmp_path / "job2").source == "set.zip"
