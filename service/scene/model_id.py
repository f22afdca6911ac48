"""The model id: one rule for every place a model is named."""

from __future__ import annotations

import re

#: A model id, the one rule for every place one is named: a scene's `name`, `elastreg train
#: --name`, a store entry's folder and manifest, the {model} segment of the API's URLs. A letter
#: or digit first: never "." or "..", nor a hidden folder (the store's temporaries, .ID-*, and
#: the entries it sets aside, ..ID-*); then only URL-unreserved characters, so a URL needs no
#: escaping; 64 at most.
MODEL_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
MODEL_ID_RULE = "must start with a letter or digit and hold only letters, digits, '_', '.' and '-' (64 at most)"


def check_model_id(model_id: str) -> str:
    """`model_id` if it is one (MODEL_ID), else a ValueError that says the rule."""
    if not isinstance(model_id, str) or not MODEL_ID.fullmatch(model_id):
        raise ValueError(f"model id {model_id!r:.80} {MODEL_ID_RULE}")
    return model_id
