"""The model and policy a filter node runs, loaded and checked against each other.

Used by the filter node at start-up (:mod:`tpsr_ros.filter_node`) and by anything that
starts one and wants its refusals first (``learner closed-loop``), without the node.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from tpsr_ros.core.episodes import DEFAULT_IMAGE_SHAPE
from tpsr_ros.core.errors import ConfigError, TpsrError
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.io.model_io import load_model, model_fingerprint, model_stream_spec, read_metadata
from tpsr_ros.io.policy import TRUE_POSITION, Policy, load_policy
from tpsr_ros.io.stream_spec import StreamSpec

__all__ = [
    "ACTION_TOPIC",
    "IMAGE_TOPIC",
    "FilterInputs",
    "input_topics",
    "load_filter_inputs",
]

IMAGE_TOPIC = "/camera/image_raw"
ACTION_TOPIC = "/action"


@dataclass(frozen=True)
class FilterInputs:
    """The model and policy a filter node runs, checked against each other and its topics."""

    model: StateModel
    fingerprint: str
    metadata: dict[str, Any]
    image_shape: tuple[int, int]
    policy: Policy | None
    spec: StreamSpec | None = None
    """The input streams of a model learned on the step grid; None: exact-stamp pairing."""


def input_topics(model_path: str) -> tuple[str, str] | None:
    """Camera and command topics a step-grid model reads, relative (no leading ``/``).

    None for exact-pairing models and for a model that cannot be read (loading it
    reports why).
    """
    try:
        spec = model_stream_spec(model_path, read_metadata(model_path)) if model_path else None
    except TpsrError:
        return None
    if spec is None:
        return None
    return spec.image_topic.lstrip("/"), spec.action_topic.lstrip("/")


def _training_topics(metadata: dict[str, Any]) -> set[tuple[str, str]]:
    bags = metadata.get("training", {}).get("bags") or []
    found = set()
    for bag in bags:
        topics = bag.get("topics") if isinstance(bag, dict) else None
        if isinstance(topics, dict) and topics.get("image") and topics.get("action"):
            found.add((str(topics["image"]), str(topics["action"])))
    return found


def load_filter_inputs(
    model_path: str,
    policy_path: str = "",
    *,
    check_topics: bool = True,
    image_topic: str = IMAGE_TOPIC,
    action_topic: str = ACTION_TOPIC,
    namespace: str = "/",
) -> FilterInputs:
    """Load the model (and policy) and refuse a combination the filter node cannot run.

    Refused, each with a one-line :class:`~tpsr_ros.core.errors.TpsrError`: no model; an
    unreadable model or policy; a true-position policy (it needs the ground truth); a policy
    trained for another model (fingerprint), or for other state dimension or number of
    actions, or another environment than the model's; a model whose images are not
    ``H x W x 3``; and, unless ``check_topics`` is false, a model trained on other topics:
    every training bag recorded in the model names its image and action topics, and each
    pair must equal ``(image_topic, action_topic)``, the node's fully resolved subscription
    names (after namespace and ``-r`` remapping), either as recorded or moved into the
    node's ``namespace`` (a model trained on ``/camera/image_raw`` runs a filter in
    ``/robot1`` on ``/robot1/camera/image_raw``). A model recording no topics is accepted.
    """
    if not model_path:
        raise ConfigError("no model given: pass -p model:=MODEL (a file from `learner fit`)")
    model = load_model(model_path)
    metadata = read_metadata(model_path)
    fingerprint = model_fingerprint(model)
    training = metadata.get("training", {})
    spec = model_stream_spec(model_path, metadata)
    shape = tuple(training.get("image_shape") or DEFAULT_IMAGE_SHAPE)
    if spec is not None:
        shape = (spec.preprocessing.height, spec.preprocessing.width)
    elif len(shape) != 2 or shape[0] * shape[1] * 3 != model.obs_size:
        raise ConfigError(
            f"model {model_path} takes {model.obs_size} observation values, not the rgb8 "
            f"pixels of {shape} images"
        )
    if check_topics:
        subscribed = (image_topic, action_topic)
        prefix = namespace.rstrip("/")
        for pair in sorted(_training_topics(metadata)):
            if pair != subscribed and (prefix + pair[0], prefix + pair[1]) != subscribed:
                raise ConfigError(
                    f"model {model_path} was trained on {pair[0]} and {pair[1]}, but the "
                    f"node subscribes {subscribed[0]} and {subscribed[1]} (remap with -r, or "
                    "-p check_topics:=false to accept)"
                )
    policy = None
    if policy_path:
        policy = load_policy(policy_path)
        if policy.representation == TRUE_POSITION:
            raise ConfigError(
                f"policy {policy_path} acts on the true position, which the filter node "
                "does not have; use a policy fitted on this model's states"
            )
        policy.check_model(fingerprint, f"model {model_path}")
        if policy.state_dim != model.state_dim or policy.n_actions != model.n_actions:
            raise ConfigError(
                f"policy {policy_path} takes {policy.state_dim}-dimensional states and "
                f"{policy.n_actions} actions, the model has {model.state_dim} and "
                f"{model.n_actions}"
            )
        environment = training.get("environment")
        if isinstance(environment, str):
            policy.check_environment(environment)
    return FilterInputs(
        model, fingerprint, metadata, (int(shape[0]), int(shape[1])), policy, spec
    )
