"""The model and policy a filter node runs, checked against each other and its topics.

Pure checks of an opened :class:`~tpsr_ros.io.model_io.ModelFile`: used by the filter node at
start-up (:mod:`tpsr_ros.filter_node`) and by anything that starts one and wants its
refusals first (``learner closed-loop``), which then hands over what it opened.
"""

from __future__ import annotations

from dataclasses import dataclass

from tpsr_ros.core.episodes import DEFAULT_IMAGE_SHAPE
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.state_model import StateModel
from tpsr_ros.io.model_io import ModelFile
from tpsr_ros.io.policy import TRUE_POSITION, Policy
from tpsr_ros.io.stream_spec import StreamSpec

__all__ = [
    "ACTION_TOPIC",
    "IMAGE_TOPIC",
    "FilterInputs",
    "check_policy",
    "filter_inputs",
    "input_topics",
    "model_image_shape",
]

IMAGE_TOPIC = "/camera/image_raw"
ACTION_TOPIC = "/action"


@dataclass(frozen=True)
class FilterInputs:
    """The model and policy a filter node runs, checked against each other and its topics."""

    model_file: ModelFile
    image_shape: tuple[int, int]
    policy: Policy | None

    @property
    def model(self) -> StateModel:
        """The state model."""
        return self.model_file.model

    @property
    def fingerprint(self) -> str:
        """The model's fingerprint."""
        return self.model_file.fingerprint

    @property
    def spec(self) -> StreamSpec | None:
        """The input streams of a model learned on the step grid; None: exact-stamp pairing."""
        return self.model_file.spec


def input_topics(model_file: ModelFile) -> tuple[str, str] | None:
    """Camera and command topics a step-grid model reads, relative (no leading ``/``).

    None for exact-pairing models (they read the simulator's topics).
    """
    spec = model_file.spec
    if spec is None:
        return None
    return spec.image_topic.lstrip("/"), spec.action_topic.lstrip("/")


def _training_topics(model_file: ModelFile) -> set[tuple[str, str]]:
    bags = model_file.training.get("bags") or []
    found = set()
    for bag in bags if isinstance(bags, list) else []:
        topics = bag.get("topics") if isinstance(bag, dict) else None
        if isinstance(topics, dict) and topics.get("image") and topics.get("action"):
            found.add((str(topics["image"]), str(topics["action"])))
    return found


def model_image_shape(model_file: ModelFile) -> tuple[int, int]:
    """The image size the model reads, refusing a model whose images are not ``H x W x 3``."""
    if model_file.spec is not None:
        prep = model_file.spec.preprocessing
        return int(prep.height), int(prep.width)
    shape = tuple(model_file.training.get("image_shape") or DEFAULT_IMAGE_SHAPE)
    size = model_file.model.obs_size
    if len(shape) != 2 or not all(isinstance(n, int) for n in shape) or (
        shape[0] * shape[1] * 3 != size
    ):
        raise ConfigError(
            f"model {model_file.path} takes {size} observation values, not the rgb8 pixels of "
            f"{shape} images"
        )
    return int(shape[0]), int(shape[1])


def check_policy(policy: Policy, model_file: ModelFile, policy_path: str) -> None:
    """Refuse a policy the filter node cannot run with this model."""
    if policy.representation == TRUE_POSITION:
        raise ConfigError(
            f"policy {policy_path} acts on the true position, which the filter node does not "
            "have; use a policy fitted on this model's states"
        )
    policy.check_model(model_file.fingerprint, f"model {model_file.path}")
    model = model_file.model
    if policy.state_dim != model.state_dim or policy.n_actions != model.n_actions:
        raise ConfigError(
            f"policy {policy_path} takes {policy.state_dim}-dimensional states and "
            f"{policy.n_actions} actions, the model has {model.state_dim} and {model.n_actions}"
        )
    if model_file.environment is not None:
        policy.check_environment(model_file.environment)


def filter_inputs(
    model_file: ModelFile,
    policy: tuple[Policy, str] | None = None,
    *,
    check_topics: bool = True,
    image_topic: str = IMAGE_TOPIC,
    action_topic: str = ACTION_TOPIC,
    namespace: str = "/",
) -> FilterInputs:
    """Check the opened model (and ``(policy, its path)``) and refuse what the node cannot run.

    Refused, each with a one-line :class:`~tpsr_ros.core.errors.TpsrError`: a true-position
    policy (it needs the ground truth); a policy trained for another model (fingerprint),
    or for other state dimension or number of actions, or another environment than the
    model's; a model whose images are not ``H x W x 3``; and, unless ``check_topics`` is
    false, a model trained on other topics: every training bag recorded in the model names
    its image and action topics, and each pair must equal ``(image_topic, action_topic)``,
    the node's fully resolved subscription names (after namespace and ``-r`` remapping),
    either as recorded or moved into the node's ``namespace`` (a model trained on
    ``/camera/image_raw`` runs a filter in ``/robot1`` on ``/robot1/camera/image_raw``). A
    model recording no topics is accepted.
    """
    shape = model_image_shape(model_file)
    if check_topics:
        subscribed = (image_topic, action_topic)
        prefix = namespace.rstrip("/")
        for pair in sorted(_training_topics(model_file)):
            if pair != subscribed and (prefix + pair[0], prefix + pair[1]) != subscribed:
                raise ConfigError(
                    f"model {model_file.path} was trained on {pair[0]} and {pair[1]}, but the "
                    f"node subscribes {subscribed[0]} and {subscribed[1]} (remap with -r, or "
                    "-p check_topics:=false to accept)"
                )
    if policy is not None:
        check_policy(policy[0], model_file, policy[1])
    return FilterInputs(model_file, shape, None if policy is None else policy[0])
