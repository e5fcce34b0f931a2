"""Request dependencies (``Annotated`` aliases): settings, the job operations, the authenticated owner, and a
job the owner may see. The app keeps its long-lived objects in ``app.state.services`` (``service.app`` builds
them from the composition root, ``service.compose``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.compose import Components
from service.core.coord import Coordinator
from service.core.settings import Settings
from service.jobs.intake import UploadIntake
from service.jobs.manifest import Manifest
from service.jobs.ops import JobOps
from service.jobs.store import JobNotFound
from service.surveys.registry import SurveyRegistry

from .errors import api_error


@dataclass
class Services:
    settings: Settings
    coord: Coordinator
    jobs: JobOps
    surveys: SurveyRegistry
    intake: UploadIntake

    @classmethod
    def of(cls, c: Components) -> Services:
        return cls(c.settings, c.coord, c.jobs, c.surveys, UploadIntake(c.settings, c.jobs, c.coord, c.idempotency))


def get_services(request: Request) -> Services:
    return request.app.state.services


ServicesDep = Annotated[Services, Depends(get_services)]


def get_settings(services: ServicesDep) -> Settings:
    return services.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_jobs(services: ServicesDep) -> JobOps:
    return services.jobs


JobsDep = Annotated[JobOps, Depends(get_jobs)]


def get_surveys(services: ServicesDep) -> SurveyRegistry:
    return services.surveys


SurveysDep = Annotated[SurveyRegistry, Depends(get_surveys)]

_bearer = HTTPBearer(auto_error=False, description="API key: `Authorization: Bearer <key>`")


def require_owner(settings: SettingsDep,
                  creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> str:
    """The owner of the presented API key; 401 without one (keys are never accepted in the query string)."""
    challenge = {"WWW-Authenticate": "Bearer"}
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise api_error(401, "unauthorized", "send an API key as 'Authorization: Bearer <key>'", challenge)
    owner = settings.owner_of(creds.credentials)
    if owner is None:
        raise api_error(401, "unauthorized", "unknown API key", challenge)
    return owner


OwnerDep = Annotated[str, Depends(require_owner)]


def owned_job(job_id: str, owner: OwnerDep, jobs: JobsDep) -> Manifest:
    """The job if it belongs to the caller; another owner's job is reported exactly like a missing one."""
    try:
        return jobs.get(job_id, owner)
    except JobNotFound:
        raise api_error(404, "job_not_found", f"no job {job_id!r}") from None


JobDep = Annotated[Manifest, Depends(owned_job)]
