"""The session settings are defined once (service/registration/settings.py): the API's request
schema, its echo and the solver's options all follow that one list."""

import dataclasses

import pytest
from pydantic import ValidationError

from service.api.schemas.sessions import SessionConfigOut, SessionCreate, SessionSettings
from service.api.work import _FIELDS
from service.registration.engine import SolveOptions
from service.registration.settings import NAMES, OPTIMIZERS, SETTINGS, SessionConfig

API_ONLY = {"skip_stale"}  # how the WebSocket queues frames: the transport's, not the engine's


def test_request_schema_is_the_settings():
    assert set(SessionSettings.model_fields) - API_ONLY == set(NAMES)
    assert set(SessionCreate.model_fields) - API_ONLY == set(NAMES) | {"model"}


def test_echo_is_the_settings():
    assert set(SessionConfigOut.model_fields) - API_ONLY == set(NAMES) | {"model"}
    assert set(_FIELDS) | {"support", "matching", "outputs"} == set(NAMES)


def test_defaults_and_docs_come_from_the_settings():
    body = SessionCreate(model="m")
    for f in SETTINGS:
        assert SessionCreate.model_fields[f.name].description == f.metadata["doc"] != ""
        value = getattr(body, f.name)
        assert (tuple(value) if f.name == "outputs" else value) == f.default, f.name


def test_bounds_come_from_the_settings():
    with pytest.raises(ValidationError, match="max_iter"):
        SessionCreate(model="m", max_iter=0)
    # no upper bound of its own: the server's cap is the one (tests/api/test_errors.py)
    assert SessionCreate(model="m", max_iter=10**9).max_iter == 10**9
    with pytest.raises(ValidationError, match="gtol"):
        SessionCreate(model="m", gtol=1.5)
    with pytest.raises(ValidationError, match="optimizer"):
        SessionCreate(model="m", optimizer="newton")
    # null means the default for numbers and switches, never for a choice
    assert SessionCreate(model="m", max_iter=None, warm_start=None).max_iter is None
    with pytest.raises(ValidationError, match="method"):
        SessionCreate(model="m", method=None)


def test_solve_options_take_the_settings_of_their_name():
    config = dataclasses.replace(
        SessionConfig(),
        alpha=2e-7,
        gtol=3e-5,
        max_iter=17,
        force_bound=0.5,
        time_budget_ms=40.0,
        precondition=True,
        optimizer=OPTIMIZERS[1],
    )
    o = SolveOptions.of(config)
    assert (o.alpha, o.gtol, o.max_iter, o.force_bound, o.precondition, o.optimizer) == (
        2e-7,
        3e-5,
        17,
        0.5,
        True,
        OPTIMIZERS[1],
    )
    assert o.time_budget == pytest.approx(0.04)
    assert SolveOptions.of(SessionConfig(alpha=1.0, gtol=0.1)).time_budget is None


def test_defaults_are_immutable():
    from service.registration.settings import setting

    with pytest.raises(TypeError):
        setting(["displacement"], "a list would be shared between sessions")
