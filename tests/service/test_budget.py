"""One set of training-budget rules (``TrainConfig.validate_budget``), and every entry point
says the same about the same bad budget: the library, the CLI (``roguenerf finetune``) and the
API (``POST /scenes/{id}/finetune``), each called for real."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from roguecli import app as cli_app
from roguenerf.errors import InputError
from roguenerf.training import TrainConfig

# (steps, minutes, the library's message; None: a valid request budget)
CASES = [
    pytest.param(0, None, "steps: expected > 0, got 0", id="steps-0"),
    pytest.param(-1, None, "steps: expected > 0, got -1", id="steps-minus-1"),
    pytest.param(None, 0.0, "minutes: expected a number > 0, got 0", id="minutes-0"),
    pytest.param(None, -1.0, "minutes: expected a number > 0, got -1", id="minutes-minus-1"),
    pytest.param(None, float("nan"), "minutes must be a finite number > 0, got nan", id="minutes-nan"),
    pytest.param(None, float("inf"), "minutes must be a finite number > 0, got inf", id="minutes-inf"),
    pytest.param(3, 1.0, "give either minutes or steps, not both", id="both"),
    pytest.param(None, None, None, id="none"),
]


def _cli_name(message: str) -> str:
    """The library's message as the CLI spells its flags."""
    for name in ("steps", "minutes"):
        message = message.replace(f"{name}:", f"--{name}:").replace(f"{name} must", f"--{name} must")
        message = message.replace(f"either {name}", f"either --{name}").replace(f"or {name}", f"or --{name}")
    return message


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    from service.app import create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path_factory.mktemp("data"))
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.mark.parametrize("steps, minutes, message", CASES)
def test_library_cli_and_api_agree_on_a_budget(steps, minutes, message, api, tmp_path):
    # The library: the rule's owner.
    if message is None:
        TrainConfig.validate_budget(steps, minutes)
    else:
        with pytest.raises(InputError) as info:
            TrainConfig.validate_budget(steps, minutes)
        assert str(info.value) == message

    # The CLI: refused before the scene is read (a missing one), exit 2, one line, nothing written.
    args = ["finetune", str(tmp_path / "no_scene"), "--scratch", "--output", str(tmp_path / "out")]
    args += [] if steps is None else ["--steps", str(steps)]
    args += [] if minutes is None else ["--minutes", str(minutes)]
    result = CliRunner().invoke(cli_app, args)
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output and not (tmp_path / "out").exists()
    if message is None:  # no budget: the plan's default; the next complaint is the scene
        assert f"scene directory {tmp_path / 'no_scene'} does not exist" in result.stderr
    else:
        assert f"error: {_cli_name(message)}" in result.stderr, result.stderr

    # The API: 422 with the same words, the field named where there is one.
    body = {k: v for k, v in (("steps", steps), ("minutes", minutes)) if v is not None}
    r = api.post("/scenes/0123456789abcdef0123456789abcdef/finetune", content=json.dumps(body),
                 headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["code"] == "validation_error"
    if message is None:  # a queued job must state its length: the one rule the API adds (required)
        expected = "body: give exactly one of steps or minutes"
    elif message.startswith(("steps", "minutes")):
        field = message.split(":")[0].split(" ")[0]
        expected = f"{field}: {message.removeprefix(field).lstrip(': ')}"
    else:
        expected = f"body: {message}"
    assert error["message"] == f"invalid request: {expected}", error


def test_a_valid_budget_passes_every_entry_point(api):
    TrainConfig.validate_budget(5, None)
    TrainConfig.validate_budget(None, 0.5, required=True)
    # The API takes it and goes on to the scene (unknown here: 404, not 422).
    r = api.post("/scenes/0123456789abcdef0123456789abcdef/finetune", json={"minutes": 0.5})
    assert r.status_code == 404, r.text


def test_the_library_alone_also_takes_zero_and_both():
    # TrainConfig (not a request): 0 saves the starting weights and stops; both: whichever first.
    assert TrainConfig(minutes=0.0).validate().minutes == 0.0
    assert TrainConfig(steps=0).validate().steps == 0
    assert TrainConfig(steps=5, minutes=1.0).validate().steps == 5
    for bad, message in (({"minutes": float("nan")}, "minutes must be a finite number >= 0, got nan"),
                         ({"minutes": -1.0}, "minutes: expected a number >= 0, got -1"),
                         ({"steps": -2}, "steps: expected >= 0, got -2"),
                         ({"steps": 2.5}, "steps: expected an integer >= 0, got 2.5")):
        with pytest.raises(InputError) as info:
            TrainConfig(**bad).validate()
        assert str(info.value) == message
