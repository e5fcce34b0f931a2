"""The surveys: API-registered ones in ``<data>/surveys/<id>/survey.json``, the surveys file's entries read on
every call, and each survey's scan state (``state.json``).

Owners (docs/SERVICE.md, "Survey folders"): a folder belongs to the first owner who registers it. No other
owner may register it, a folder inside it or a folder around it (409 ``path_taken``); the surveys file cannot
hand it to another owner either (such an entry is skipped and logged). ``survey_owner_roots`` gives an owner
roots of their own, which no other owner may register anything under.

Paths are re-checked at every scan (:meth:`SurveyRegistry.check_folder`): the registered folder must still be
itself (not a link) and under an allowed root of its owner, else the scan records ``last_error`` on the survey
and submits nothing.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import time
import tomllib
from pathlib import Path

from pydantic import BaseModel, Field, ValidationError

from pipeline.job.markers import atomic_write_text
from service.jobs.options import JobOptionsIn

log = logging.getLogger(__name__)


class SurveyError(ValueError):
    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code


class SurveyNotFound(LookupError):
    pass


class SurveyOptions(JobOptionsIn):
    """The job options a survey's jobs get, checked when the survey is registered."""


class Survey(BaseModel):
    id: str
    owner: str
    name: str
    path: str  # resolved
    interval_s: float
    options: SurveyOptions = Field(default_factory=SurveyOptions)
    callback_url: str | None = None  # every job of this survey announces its end there (service.webhooks)
    origin: str = "api"  # api | config
    created_at: float = 0.0


class SubmittedSet(BaseModel):
    name: str
    images: int
    job_id: str
    submitted_at: float


class WaitingSet(BaseModel):
    name: str
    images: int
    reason: str


class SurveyState(BaseModel):
    last_scan_at: float = 0.0
    last_scan_seconds: float | None = None
    scans: int = 0
    last_error: str | None = None
    last_error_code: str | None = None
    waiting: list[WaitingSet] = Field(default_factory=list)  # sets seen by the last scan and not submitted, why
    sets: dict[str, SubmittedSet] = Field(default_factory=dict)  # set hash -> job
    digests: dict[str, tuple[int, int, str]] = Field(default_factory=dict)  # rel path -> (size, mtime_ns, sha256)
    # loose images only: rel path -> (size, mtime_ns, EXIF capture time or None when the file has none)
    exif_times: dict[str, tuple[int, int, float | None]] = Field(default_factory=dict)


def survey_id(owner: str, path: str) -> str:
    return "v" + hashlib.sha256(f"{owner}\0{path}".encode()).hexdigest()[:15]


def resolve_under_roots(path: str, roots: list[Path], forbidden: list[Path] = ()) -> Path:
    """The real folder ``path`` names, if it lies under an allowed root (after resolving every link) and under
    none of ``forbidden`` (other owners' own roots)."""
    if not roots:
        raise SurveyError("surveys_disabled", "no survey roots are configured (DUALPHYS_SURVEY_ROOTS)")
    try:
        real = Path(path).resolve(strict=True)
    except (OSError, RuntimeError) as e:
        raise SurveyError("path_not_found", f"no such folder: {path}") from e
    if not real.is_dir():
        raise SurveyError("path_not_found", f"not a folder: {path}")
    if root_of(real, roots) is None or root_of(real, list(forbidden)) is not None:
        raise SurveyError("path_not_allowed", f"{path} is not under an allowed survey root")
    return real


def root_of(real: Path, roots: list[Path]) -> Path | None:
    """The (resolved) root of ``roots`` that ``real`` lies under, or None."""
    for root in roots:
        r = Path(root).resolve()
        if real == r or real.is_relative_to(r):
            return r
    return None


def overlaps(a: str, b: str) -> bool:
    """Two resolved folders are the same, or one lies inside the other."""
    pa, pb = Path(a), Path(b)
    return pa == pb or pa.is_relative_to(pb) or pb.is_relative_to(pa)


class SurveyRegistry:
    """API-registered surveys live in ``<data>/surveys/<id>/survey.json``; config-file surveys are read from
    ``surveys_file`` each time; both keep their scan state in ``<data>/surveys/<id>/state.json``."""

    def __init__(self, surveys_dir: Path, roots: list[Path], surveys_file: Path | None, min_interval_s: float,
                 max_iterations: int | None = None, owner_roots: dict[str, list[Path]] | None = None):
        self.dir = Path(surveys_dir)
        self.roots = roots
        self.owner_roots = owner_roots or {}
        self.surveys_file = surveys_file
        self.min_interval_s = min_interval_s
        self.max_iterations = max_iterations  # the server's limit on a job's iterations (None: none)

    def roots_for(self, owner: str) -> tuple[list[Path], list[Path]]:
        """(roots ``owner`` may register under, roots reserved to other owners)."""
        own = list(self.roots) + list(self.owner_roots.get(owner, []))
        others = [r for o, rs in self.owner_roots.items() if o != owner for r in rs]
        return own, others

    def resolve(self, owner: str, path: str) -> Path:
        own, others = self.roots_for(owner)
        if not own:
            raise SurveyError("surveys_disabled", "no survey roots are configured (DUALPHYS_SURVEY_ROOTS)")
        return resolve_under_roots(path, own, others)

    def check_folder(self, survey: Survey, surveys: list[Survey] | None = None) -> Path:
        """At every scan: the survey's folder is still the folder that was registered (not replaced by a link),
        still under an allowed root of its owner, and no earlier survey of another owner claims it. Returns the
        root it lies under; raises SurveyError otherwise."""
        registered = Path(survey.path)
        try:
            real = Path(os.path.realpath(registered, strict=True))
        except OSError as e:
            raise SurveyError("path_not_found", f"the survey folder {survey.path} is missing") from e
        if real != registered or not real.is_dir():
            raise SurveyError("path_changed", f"the survey folder {survey.path} is no longer a folder of its own "
                                              f"(it was replaced by a link or a file); it is not scanned")
        own, others = self.roots_for(survey.owner)
        root = root_of(real, own)
        if root is None or root_of(real, others) is not None:
            raise SurveyError("path_not_allowed", f"the survey folder {survey.path} is no longer under an allowed "
                                                  f"survey root; it is not scanned")
        if self.claimed_by_other(survey, surveys if surveys is not None else self.all()):
            raise SurveyError("path_taken", f"the survey folder {survey.path} belongs to another owner's survey")
        return root

    @staticmethod
    def claimed_by_other(survey: Survey, surveys: list[Survey]) -> bool:
        """Another owner's survey that came first (API surveys by creation time, then the surveys file in
        order) covers this survey's folder, lies inside it or around it."""
        for other in surveys:
            if other.id == survey.id:
                return False  # everything after this one came later
            if other.owner != survey.owner and overlaps(other.path, survey.path):
                return True
        return False

    def _check_options(self, options: SurveyOptions) -> None:
        if self.max_iterations is not None and (why := options.over_limit(self.max_iterations)) is not None:
            raise SurveyError("invalid_options", why)

    def _folder(self, sid: str) -> Path:
        if not (sid.startswith("v") and sid[1:].isalnum() and len(sid) == 16):
            raise SurveyNotFound(sid)
        return self.dir / sid

    def register(self, owner: str, path: str, interval_s: float, name: str | None,
                 options: SurveyOptions, callback_url: str | None = None) -> Survey:
        self._check_options(options)
        real = self.resolve(owner, path)
        if interval_s < self.min_interval_s:
            raise SurveyError("interval_too_short", f"interval_s must be at least {self.min_interval_s}")
        sid = survey_id(owner, str(real))
        existing = self.all()
        if any(s.id == sid for s in existing):
            raise SurveyError("survey_exists", f"{real} is already registered as survey {sid}")
        if any(s.owner != owner and overlaps(s.path, str(real)) for s in existing):
            raise SurveyError("path_taken", f"{path} (or a folder inside or around it) belongs to another owner's "
                                            f"survey; a folder has one owner")
        s = Survey(id=sid, owner=owner, name=name or real.name, path=str(real), interval_s=interval_s,
                   options=options, callback_url=callback_url, origin="api", created_at=time.time())
        atomic_write_text(self._folder(sid) / "survey.json", s.model_dump_json(indent=2))
        return s

    def all(self) -> list[Survey]:
        """API surveys (oldest first), then the surveys file's entries, leaving out entries that would hand a
        folder another owner already has (first claim wins, see the module docstring)."""
        out: list[Survey] = []
        if self.dir.is_dir():
            for p in sorted(self.dir.glob("v*/survey.json")):
                try:
                    out.append(Survey.model_validate_json(p.read_text()))
                except (ValidationError, OSError) as e:
                    log.error("unreadable survey %s: %s", p, e)
        out.sort(key=lambda s: (s.created_at, s.id))
        for s in self.from_config():
            if any(o.owner != s.owner and overlaps(o.path, s.path) for o in out):
                log.error("surveys file %s: %s of owner %r skipped: the folder belongs to another owner's survey",
                          self.surveys_file, s.path, s.owner)
                continue
            out.append(s)
        return out

    def from_config(self) -> list[Survey]:
        if self.surveys_file is None:
            return []
        try:
            data = tomllib.loads(Path(self.surveys_file).read_text(encoding="utf-8"))
        except (OSError, tomllib.TOMLDecodeError) as e:
            log.error("cannot read surveys file %s: %s", self.surveys_file, e)
            return []
        out = []
        for i, entry in enumerate(data.get("survey", [])):
            try:
                owner = str(entry["owner"])
                real = self.resolve(owner, str(entry["path"]))
                interval = max(float(entry.get("interval_s", 3600)), self.min_interval_s)
                options = SurveyOptions(**entry.get("options", {}))
                self._check_options(options)
                out.append(Survey(id=survey_id(owner, str(real)), owner=owner, name=str(entry.get("name", real.name)),
                                  path=str(real), interval_s=interval, options=options, origin="config",
                                  callback_url=entry.get("callback_url")))
            except (KeyError, TypeError, ValueError, SurveyError, ValidationError) as e:
                log.error("surveys file %s, entry %d skipped: %s", self.surveys_file, i, e)
        return out

    def get(self, sid: str, owner: str | None = None) -> Survey:
        for s in self.all():
            if s.id == sid and (owner is None or s.owner == owner):
                return s
        raise SurveyNotFound(sid)

    def delete(self, sid: str, owner: str) -> None:
        s = self.get(sid, owner)
        if s.origin != "api":
            raise SurveyError("survey_from_config", "this survey comes from the surveys file; edit that file")
        shutil.rmtree(self._folder(sid), ignore_errors=True)

    def state(self, sid: str) -> SurveyState:
        try:
            return SurveyState.model_validate_json((self._folder(sid) / "state.json").read_text())
        except FileNotFoundError:
            return SurveyState()
        except (ValidationError, OSError) as e:
            log.error("survey %s: unreadable state, starting afresh: %s", sid, e)
            return SurveyState()

    def save_state(self, sid: str, state: SurveyState) -> None:
        atomic_write_text(self._folder(sid) / "state.json", state.model_dump_json(indent=1))
