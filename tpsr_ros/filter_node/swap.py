"""Model swaps of a running filter node: what is asked, what is checked, what is announced.

A new model arrives as a path (``ros2 param set`` of ``model``, or a ``tpsr/model_update``
message: JSON ``{"path": ..., "fingerprint": ..., "policy": ..., "version": ...}``, only
``path`` required). :func:`checked_inputs` opens it once and refuses, with the reason, a
model the node cannot run in place of the one it runs: another input contract (image size,
actions, step grid), other topics, a fingerprint other than the one announced, a policy for
another model. What the node runs is acknowledged on the latched ``tpsr/model_info`` as
JSON (:func:`model_info`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.filter_inputs import FilterInputs, filter_inputs
from tpsr_ros.io.messages import jazzy_typestore
from tpsr_ros.io.model_io import metadata_field, open_model
from tpsr_ros.io.policy import load_policy

__all__ = [
    "MODEL_MESSAGE_TYPE",
    "ModelUpdate",
    "checked_inputs",
    "model_info",
    "parse_update",
    "string_msg",
]

MODEL_MESSAGE_TYPE = "std_msgs/msg/String"
MAX_UPDATE_CHARS = 4096
"""Longest ``tpsr/model_update`` message read (a path and a few fields)."""


@dataclass(frozen=True)
class ModelUpdate:
    """A request to run another model (and its policy)."""

    path: str
    fingerprint: str | None = None
    policy: str | None = None
    version: int | None = None


def parse_update(text: str) -> ModelUpdate:
    """The update a ``tpsr/model_update`` message asks for, or a ``ConfigError`` saying why
    it cannot be read."""
    if len(text) > MAX_UPDATE_CHARS:
        raise ConfigError(f"a model update of {len(text)} characters (at most {MAX_UPDATE_CHARS})")
    try:
        value = json.loads(text)
    except ValueError as exc:
        raise ConfigError(f"a model update that is not JSON ({exc})") from None
    if not isinstance(value, dict) or not isinstance(value.get("path"), str) or not value["path"]:
        raise ConfigError('a model update must be a JSON object with a "path" string')
    for key in ("fingerprint", "policy"):
        if value.get(key) is not None and not isinstance(value[key], str):
            raise ConfigError(f'the model update\'s "{key}" must be a string')
    version = value.get("version")
    if version is not None and (isinstance(version, bool) or not isinstance(version, int)):
        raise ConfigError('the model update\'s "version" must be an integer')
    policy = value.get("policy") or None
    return ModelUpdate(value["path"], value.get("fingerprint"), policy, version)


def _contract(inputs: FilterInputs) -> tuple[Any, ...]:
    """What a model asks of the node's inputs: it must not change while the node runs."""
    model, spec = inputs.model, inputs.spec
    return (
        model.obs_size,
        model.n_actions,
        inputs.image_shape,
        None if spec is None else json.dumps(spec.as_dict(), sort_keys=True),
        inputs.model_file.environment,
    )


def checked_inputs(
    update: ModelUpdate,
    current: FilterInputs,
    *,
    check_topics: bool,
    image_topic: str,
    action_topic: str,
    namespace: str,
) -> tuple[FilterInputs, str | None]:
    """The inputs the node would run after ``update``, checked as at start-up and against
    the running ones, and a note when the policy no longer fits (the node then tracks
    without commanding). A ``TpsrError`` says why the model is refused."""
    model_file = open_model(update.path)
    if update.fingerprint is not None and not model_file.fingerprint.startswith(update.fingerprint):
        raise ConfigError(
            f"{update.path} has fingerprint {model_file.fingerprint[:12]}, not the announced "
            f"{update.fingerprint[:12]}"
        )
    policy = None
    note = None
    if update.policy is not None:
        policy = (load_policy(update.policy), update.policy)
    elif current.policy is not None:
        if current.policy.model_fingerprint == model_file.fingerprint:
            policy = (current.policy, "the running policy")
        else:
            note = (
                f"the running policy is for model {current.policy.model_fingerprint[:12]}: "
                "tracking without commanding until a policy for this model is set"
            )
    inputs = filter_inputs(
        model_file,
        policy,
        check_topics=check_topics,
        image_topic=image_topic,
        action_topic=action_topic,
        namespace=namespace,
    )
    if _contract(inputs) != _contract(current):
        raise ConfigError(
            f"{update.path} reads other inputs than the running model (image size, actions, "
            "step grid or environment): start a new node for it"
        )
    return inputs, note


def model_info(
    inputs: FilterInputs, *, version: int | None, swaps: int, first_stamp_ns: int | None
) -> str:
    """The JSON of ``tpsr/model_info``: the model in use and since which step."""
    steps = metadata_field(inputs.model_file.metadata, "training", "steps")
    return json.dumps(
        {
            "fingerprint": inputs.fingerprint,
            "path": str(Path(inputs.model_file.path)),
            "version": version,
            "steps_fitted": steps if isinstance(steps, int) else None,
            "first_stamp_ns": first_stamp_ns,
            "swaps": swaps,
            "policy": None if inputs.policy is None else inputs.policy.model_fingerprint[:12],
        },
        sort_keys=True,
    )


def string_msg(text: str) -> Any:
    """A ``std_msgs/msg/String`` holding ``text``."""
    return jazzy_typestore().types[MODEL_MESSAGE_TYPE](data=text)
