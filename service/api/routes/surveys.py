"""/v1/surveys: register a survey folder with a scan interval, list, show, delete, scan now."""

from __future__ import annotations

from fastapi import APIRouter, Response

from service.api.deps import OwnerDep, ServicesDep, SettingsDep, SurveysDep
from service.api.errors import api_error
from service.api.schemas.inputs import SurveyCreate
from service.api.schemas.responses import ErrorOut, ScanQueued, SubmittedSetOut, SurveyList, SurveyOut
from service.core.dispatch import DispatchError
from service.surveys.registry import Survey, SurveyError, SurveyNotFound, SurveyRegistry
from service.webhooks.callback import CallbackRefused, check_callback_url

router = APIRouter(prefix="/v1/surveys", tags=["surveys"])
ERRORS = {s: {"model": ErrorOut} for s in (401, 404, 409, 422, 503)}
SURVEY_ERROR_STATUS = {"survey_exists": 409, "survey_from_config": 409, "path_taken": 409, "path_not_allowed": 403,
                       "surveys_disabled": 403}


def _out(registry: SurveyRegistry, s: Survey) -> SurveyOut:
    st = registry.state(s.id)
    sets = [SubmittedSetOut(set_hash=h, **v.model_dump()) for h, v in st.sets.items()]
    return SurveyOut(id=s.id, name=s.name, path=s.path, interval_s=s.interval_s, options=s.options.model_dump(),
                     callback_url=s.callback_url,
                     origin=s.origin, created_at=s.created_at, last_scan_at=st.last_scan_at or None, scans=st.scans,
                     last_error=st.last_error, last_error_code=st.last_error_code,
                     waiting=[w.model_dump() for w in st.waiting], sets=sorted(sets, key=lambda x: x.submitted_at))


def _get(registry: SurveyRegistry, survey_id: str, owner: str) -> Survey:
    try:
        return registry.get(survey_id, owner)
    except SurveyNotFound:
        raise api_error(404, "survey_not_found", f"no survey {survey_id!r}") from None


@router.post("", status_code=201, response_model=SurveyOut, responses=ERRORS, summary="Register a survey folder")
def create_survey(body: SurveyCreate, owner: OwnerDep, registry: SurveysDep, settings: SettingsDep) -> SurveyOut:
    if body.callback_url:
        try:
            check_callback_url(body.callback_url, settings.webhook_allowed_hosts,
                               settings.webhook_secret(owner) is not None)
        except CallbackRefused as e:
            raise api_error(422, e.code, str(e)) from None
    try:
        s = registry.register(owner, body.path, body.interval_s, body.name, body.options, body.callback_url or None)
    except SurveyError as e:
        raise api_error(SURVEY_ERROR_STATUS.get(e.code, 422), e.code, str(e)) from None
    return _out(registry, s)


@router.get("", response_model=SurveyList, responses=ERRORS, summary="List your survey folders")
def list_surveys(owner: OwnerDep, registry: SurveysDep) -> SurveyList:
    return SurveyList(surveys=[_out(registry, s) for s in registry.all() if s.owner == owner])


@router.get("/{survey_id}", response_model=SurveyOut, responses=ERRORS, summary="A survey and its submitted sets")
def get_survey(survey_id: str, owner: OwnerDep, registry: SurveysDep) -> SurveyOut:
    return _out(registry, _get(registry, survey_id, owner))


@router.delete("/{survey_id}", status_code=204, responses=ERRORS,
               summary="Stop scanning a survey folder (its jobs stay)")
def delete_survey(survey_id: str, owner: OwnerDep, registry: SurveysDep) -> Response:
    _get(registry, survey_id, owner)
    try:
        registry.delete(survey_id, owner)
    except SurveyError as e:
        raise api_error(SURVEY_ERROR_STATUS.get(e.code, 409), e.code, str(e)) from None
    return Response(status_code=204)


@router.post("/{survey_id}/scan", status_code=202, response_model=ScanQueued, responses=ERRORS,
             summary="Scan a survey folder now")
def scan_now(survey_id: str, owner: OwnerDep, registry: SurveysDep, services: ServicesDep) -> ScanQueued:
    s = _get(registry, survey_id, owner)
    assert services.jobs.dispatcher is not None
    try:
        return ScanQueued(survey_id=s.id, task_id=services.jobs.dispatcher.send_scan(s.id))
    except DispatchError as e:
        raise api_error(503, "broker_unavailable", str(e)) from None
