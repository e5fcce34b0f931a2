"""Service and worker settings, from the environment (prefix ``DUALPHYS_``) via pydantic-settings.

The API keys and the data folder have no defaults: a deployment must say them. Everything else has a
production default; tests and ``service.embedded.serve`` override the timings. Lists and mappings are JSON
in the environment, e.g. ``DUALPHYS_API_KEYS='{"<key>": "alice"}'``, ``DUALPHYS_SURVEY_ROOTS='["/surveys"]'``.
"""

from __future__ import annotations

import hmac
from pathlib import Path

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from pipeline.ingest.archive import ArchiveLimits

MIN_KEY_LENGTH = 16


class Settings(BaseSettings):
    """One object for the API, the worker and beat (they read the same environment)."""

    model_config = SettingsConfigDict(env_prefix="DUALPHYS_", extra="ignore", frozen=True)

    # ---- required
    api_keys: dict[SecretStr, str]
    """API key -> owner name. Keys travel only in ``Authorization: Bearer <key>``; at least 16 characters."""
    data_dir: Path
    """Job folders (``jobs/``), survey state (``surveys/``), the beat schedule. Shared by api, worker, beat."""

    # ---- Redis (broker, per-job locks, progress cache)
    redis_url: str = "redis://127.0.0.1:6379/0"
    redis_prefix: str = "dualphys"
    """Every key this service writes starts with ``<prefix>:``, the broker's keys included."""

    # ---- uploads
    max_upload_bytes: int = Field(2 << 30, gt=0)
    """Cap on one uploaded archive; refused with 413 from Content-Length or while streaming."""
    archive_max_entries: int = Field(5000, gt=0)
    archive_max_total_bytes: int = Field(4 << 30, gt=0)
    archive_max_file_bytes: int = Field(512 << 20, gt=0)
    archive_max_ratio: float = Field(200.0, gt=1)
    min_images: int = Field(3, ge=1)
    ingest_concurrency: int = Field(2, ge=1)
    """Uploads validated (unpacked and decoded) at once in the API process; more wait their turn."""
    min_free_bytes: int = Field(1 << 30, ge=0)
    """The data disk must keep this much free: /ready fails below it and uploads get 507."""
    max_iterations: int = Field(100_000, ge=1)

    # ---- worker
    device: str = "cpu"
    """Torch device of this worker's stages (``cuda`` on GPU workers)."""
    train_queue: str = "cpu"
    """Queue of the train stage: ``gpu`` when GPU workers (``-Q gpu``) exist; every other stage uses ``cpu``."""
    visibility_timeout_s: int = Field(900, ge=1)
    """Broker redelivers an unacknowledged task after this; the job lock makes the redelivery harmless."""
    restore_interval_s: int = Field(30, ge=1)
    """How often a worker looks for tasks abandoned by a dead worker (after ``visibility_timeout_s``)."""
    lock_ttl_s: float = Field(60.0, gt=0)
    """Per-job lock lifetime; the runner renews it every third of this while a stage runs."""
    lock_retry_s: float = Field(3.0, gt=0)
    """A task whose job is locked by a live runner comes back after this many seconds (a dead holder, by its
    worker's heartbeat, is taken over at once)."""
    redis_outage_wait_s: float = Field(600.0, gt=0)
    """A stage that ended while Redis was unreachable retries recording its end and queuing the next stage (with
    backoff) this long; after that the watchdog finds the job once Redis is back."""
    watchdog_every_s: float = Field(2.0, gt=0)
    """The API's watchdog (service.jobs.watchdog) looks for unfinished jobs nobody runs this often."""
    watchdog_grace_s: float = Field(12.0, gt=0)
    """A job must look abandoned (no live runner, no queued message; unacknowledged ones count after this too)
    for this long before the watchdog re-queues its stage: longer than a hand-over between stages, a worker's
    takeover of a redelivered task (``lock_retry_s``) and a heartbeat's lifetime."""
    require_workers: bool = False
    """/ready is 503 while a queue jobs need has no live worker (``dualphys serve`` with workers sets it)."""
    max_stage_attempts: int = Field(3, ge=1)
    """A stage whose worker died this many times fails the job (code ``worker_lost``)."""
    max_tasks_per_child: int = Field(0, ge=0)
    """Replace a prefork child after this many tasks (0: never by count). Each replacement costs ~2 s."""
    max_memory_per_child_mb: int = Field(3072, ge=0)
    """Replace a prefork child after a task that left it above this resident size (0: never), so memory a
    large job took is given back; the pipeline keeps no state between stages, so reuse is otherwise safe."""

    # ---- survey folders
    survey_roots: list[Path] = []
    """Folders under which any owner may register survey folders (resolved, symlinks followed, then checked).
    A folder belongs to the first owner who registers it (a second owner gets 409 ``path_taken``)."""
    survey_owner_roots: dict[str, list[Path]] = {}
    """Owner -> folders only that owner may register survey folders under, e.g. ``{"alice": ["/surveys/alice"]}``
    (no other owner may register anything below them, even where a shared root covers them)."""
    survey_min_images: int = Field(6, ge=3)
    """A survey set is submitted only once it has this many images: smaller sets seldom survive SfM (4-5 tiny
    sets failed there in issue 13) and are listed on the survey as waiting, with the reason."""
    surveys_file: Path | None = None
    """TOML file with ``[[survey]]`` tables (name, path, owner, interval_s, options); read on every tick."""
    survey_tick_s: float = Field(30.0, gt=0)
    """Beat period; each survey is scanned when its own interval has passed."""
    survey_min_interval_s: float = Field(60.0, gt=0)
    survey_settle_s: float = Field(120.0, ge=0)
    """A set is submitted only when its newest image is at least this old (the ROV has stopped writing)."""
    survey_gap_s: float = Field(300.0, gt=0)
    """Images directly in a survey folder split into sets where capture times are further apart than this."""

    # ---- webhooks (service.webhooks)
    webhook_allowed_hosts: list[str] = []
    """Hosts a job's ``callback_url`` may name (exact names or IPs; ``.example.org`` allows its sub-domains).
    Empty: webhooks are off and a callback_url is refused (422 ``callbacks_disabled``)."""
    webhook_secrets: dict[str, SecretStr] = {}
    """Owner -> the secret their events are signed with (HMAC-SHA256); an owner without one cannot set a
    callback_url (422 ``callback_no_secret``)."""
    webhook_max_attempts: int = Field(5, ge=1)
    """Attempts per event; after the last failed one the delivery is given up (recorded on the job)."""
    webhook_backoff_s: float = Field(10.0, gt=0)
    """Wait before the second attempt; doubled for each attempt after it (capped at ``webhook_backoff_max_s``)."""
    webhook_backoff_max_s: float = Field(600.0, gt=0)
    webhook_timeout_s: float = Field(10.0, gt=0)
    """Connect and read timeout of one attempt; a receiver slower than this counts as a failed attempt."""

    # ---- object store (workers on many hosts without a shared disk; service.storage, docs/SERVICE.md)
    object_store_url: str | None = None
    """S3 endpoint (``http://store:8333``). Unset: the data folder is the only store and must be shared by the API
    and every worker. Set: manifests, logs and job files live in the bucket and each host's data folder is its copy."""
    object_store_bucket: str = "dualphys"
    object_store_prefix: str = "dualphys"
    """Every object this deployment writes is ``<prefix>/jobs/<id>/<path in the job folder>``."""
    object_store_access_key: SecretStr | None = None
    object_store_secret_key: SecretStr | None = None
    object_store_region: str = "us-east-1"

    @field_validator("object_store_url", "object_store_access_key", "object_store_secret_key", mode="before")
    @classmethod
    def _empty_is_unset(cls, v):
        return None if v == "" else v  # Compose passes ``${VAR:-}`` as an empty string

    @field_validator("api_keys")
    @classmethod
    def _keys_long_enough(cls, v: dict[SecretStr, str]) -> dict[SecretStr, str]:
        if not v:
            raise ValueError("at least one API key is required")
        for key, owner in v.items():
            if len(key.get_secret_value()) < MIN_KEY_LENGTH:
                raise ValueError(f"API keys must have at least {MIN_KEY_LENGTH} characters (owner {owner!r})")
            if not owner or not owner.replace("-", "").replace("_", "").replace(".", "").isalnum():
                raise ValueError(f"owner names are letters, digits, '-', '_' and '.': {owner!r}")
        return v

    @property
    def jobs_dir(self) -> Path:
        return self.data_dir / "jobs"

    @property
    def surveys_dir(self) -> Path:
        return self.data_dir / "surveys"

    def webhook_secret(self, owner: str) -> str | None:
        secret = self.webhook_secrets.get(owner)
        return secret.get_secret_value() if secret is not None else None

    def archive_limits(self) -> ArchiveLimits:
        return ArchiveLimits(max_entries=self.archive_max_entries, max_total_bytes=self.archive_max_total_bytes,
                             max_file_bytes=self.archive_max_file_bytes, max_ratio=self.archive_max_ratio)

    def owner_of(self, key: str) -> str | None:
        """The owner of an API key (constant-time comparison against every configured key)."""
        found = None
        for k, owner in self.api_keys.items():
            if hmac.compare_digest(k.get_secret_value().encode(), key.encode()):
                found = owner
        return found


def load_settings(**overrides) -> Settings:
    """Read the environment (plus explicit overrides); raises pydantic's ValidationError when it is incomplete."""
    return Settings(**overrides)

