"""A request's `id` is a string, an integer or absent: anything else is refused (`bad_request`),
never converted (pydantic's lax union made `1.0` and `true` the id 1, and `false` 0, so the
reply named another request than the one sent)."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from rigctl.apps.daemon.messages import Reply, Request, decode_request


@pytest.mark.parametrize("request_id", ["a", "", "x" * 200, 0, -7, 10**29, None])
def test_a_string_an_integer_or_no_id_is_taken_as_given(request_id):
    for request in (Request.model_validate({"id": request_id, "cmd": "ping"}),
                    Request.model_validate_json(json.dumps({"id": request_id, "cmd": "ping"}))):
        assert request.id == request_id and type(request.id) is type(request_id)
    assert Request.model_validate({"cmd": "ping"}).id is None
    echoed = json.loads(Reply(id=request_id, ok=True).model_dump_json())["id"]
    assert echoed == request_id and type(echoed) is type(request_id)


@pytest.mark.parametrize("text, says", [
    ("1.0", "a number with a fraction or an exponent"), ("1.5", "a number"), ("-0.0", "a number"),
    ("1e3", "a number"), ("NaN", "a number"), ("Infinity", "a number"),
    ("true", "a boolean"), ("false", "a boolean"), ("[1]", "a list"), ("[]", "a list"),
    ('{"a": 1}', "an object")])
def test_any_other_id_is_refused_naming_what_it_is(text, says):
    payload = f'{{"id": {text}, "cmd": "status"}}'.encode()
    for parse in (lambda: Request.model_validate(decode_request(payload)),  # the daemon's path
                  lambda: Request.model_validate_json(payload)):  # a local run's
        with pytest.raises(ValidationError) as refused:
            parse()
        (problem,) = refused.value.errors()
        assert problem["loc"] == ("id",)
        assert problem["msg"].startswith(f"an id is a string or an integer, not {says}")
