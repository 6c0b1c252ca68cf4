"""Named settings of the fit and the planner: the project's two and the guide's.

A preset is a set of changes to the dataclass defaults of :class:`TPSRConfig` and
:class:`FQIConfig`, which stay the guide's values field by field (figure 4.5 with rank 5,
section 4.3; the fitted Q of section 4.1), the reference path of the algorithm:

- ``guide``: no change. Every model and score is the guide's algorithm as documented.
- ``best``: the configuration chosen by the project's own experiments (docs/results.md,
  "Studies"): k-means kernel centres, history/test features normalised to sum 1, rank 8,
  every action's operators pooled, the observation whitening keeping 95 % of the
  camera's variance; fitted Q in predictive units with an ensemble of 5 x 100 centres.
  For a robot that turns (its actions include a turn rate, ``angular.z``: the ``drive``
  environment, a differential-drive robot's ``cmd_vel``): 20 history/test dimensions,
  rank 16 and operators pooled half-way, since its camera's view depends on a third
  coordinate, the heading, and on which way each action turns it (docs/results.md,
  "drive").
- ``predictive`` (the default): ``best`` with ``P_TH``'s tests from the current step,
  histories of the last two images (chosen on the selection seeds in ``partial-strip``,
  407.8 to 422.4, and higher on the fresh seeds in four environments of five; "A
  predictive state: two images of history", where two images also had a third more
  recorded steps), a window starting at every step of the
  training run (overlapping, so the spectral start learns from every window the refinement
  runs over, not a third of them; "A predictive state: every step a window"), and the
  spectral model refined through its filter (:mod:`tpsr_ros.core.refine`), from a start
  whose typical step carries 0.3 of the previous state forward (first chosen among 0, 0.3,
  0.5 and 0.7 with histories of one image, whose ``partial-strip`` runs, run again, put the
  four level: docs/results.md, "A predictive state: the carried start"; it rests on the study
  with two images of history, 422.4 against 363.3 without a carry on the selection seeds in
  ``partial-strip``, which costs ``full`` 2.8 points: "the carry with two images of
  history"), and only where the previous image helps to predict the
  next ones (``refine_carry_rule`` ``aliased``, :mod:`tpsr_ros.core.history_gain`: not in
  ``full``, whose image tells the place); a robot that turns carries nothing (the carried
  start loses its heading: in ``drive`` the heading's R² falls from 0.89 at 0 to 0.63 at
  0.7, the score from 353.7 to 145.5), and its observation kernel is widened until the
  median image's weights spread over two effective centres (``obs_effective_centres``,
  :mod:`tpsr_ros.core.kernel_width`: whitened to 95 % of the variance its camera keeps about
  50 dimensions, where the guide's width gives each image to one centre; "A predictive
  state: the observation kernel's width"); a fitted-Q member that diverges is refitted alone
  (``fqi.refit member``), not the whole ensemble, which rescued every run where refitting
  the whole ensemble collapsed ("A predictive state: refitting a diverged planner"). On
  the headline's fresh seeds, from the same 24000 recorded steps, it is at least level with
  ``best`` in every environment and above it in ``partial-strip`` ("A predictive state").

Options given explicitly (``learner fit --rank 5``, ``--set tpsr.rank=5``) change single
fields of a preset; :func:`departures` names them, so a model records its preset and what
differs from it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.tpsr import TPSRConfig

__all__ = [
    "DEFAULT_PRESET",
    "PRESETS",
    "TURN_COMPONENT",
    "Preset",
    "departures",
    "get_preset",
    "turns",
]


def _frozen(values: Mapping[str, Any]) -> Mapping[str, Any]:
    return MappingProxyType(dict(values))


@dataclass(frozen=True)
class Preset:
    """Changes to the guide's defaults of the fit (``tpsr``) and the planner (``fqi``).

    ``robot_tpsr`` holds further changes for robot bags (camera and commands resampled on
    a step grid), applied on top of ``tpsr``; ``turning_tpsr`` further changes for a robot
    that turns (:func:`turns`), applied last.
    """

    name: str
    summary: str
    tpsr: Mapping[str, Any] = field(default_factory=dict)
    fqi: Mapping[str, Any] = field(default_factory=dict)
    robot_tpsr: Mapping[str, Any] = field(default_factory=dict)
    turning_tpsr: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for attr in ("tpsr", "fqi", "robot_tpsr", "turning_tpsr"):
            object.__setattr__(self, attr, _frozen(getattr(self, attr)))
        self.tpsr_config(robot=True, turning=True)  # every change must name a valid field
        self.fqi_config()

    def tpsr_values(self, *, robot: bool = False, turning: bool = False) -> dict[str, Any]:
        """The preset's TPSR changes (with the robot-bag ones when ``robot``, the turning
        robot's when ``turning``)."""
        return {
            **self.tpsr,
            **(self.robot_tpsr if robot else {}),
            **(self.turning_tpsr if turning else {}),
        }

    def tpsr_config(
        self, *, robot: bool = False, turning: bool = False, **changes: Any
    ) -> TPSRConfig:
        """The preset's TPSR parameters, then ``changes``."""
        values = {**self.tpsr_values(robot=robot, turning=turning), **changes}
        return _build(TPSRConfig, values, self.name)

    def fqi_config(self, **changes: Any) -> FQIConfig:
        """The preset's fitted-Q parameters, then ``changes``."""
        return _build(FQIConfig, {**self.fqi, **changes}, self.name)


def _build(cls: type[Any], values: Mapping[str, Any], name: str) -> Any:
    known = {f.name for f in dataclasses.fields(cls)}
    if unknown := sorted(set(values) - known):
        raise ConfigError(f"preset {name!r}: unknown {cls.__name__} fields {unknown}")
    return cls(**values)


_BEST = Preset(
    "best",
    "the one-parameter studies' choice: k-means centres, normalised history/test features, "
    "rank 8, pooled action operators, observation whitening to 95 % of the variance (a robot "
    "that turns: rank 16, 20 history/test dimensions, operators pooled half-way); "
    "fitted Q in predictive units, 5 x 100 centres",
    tpsr={
        "center_selection": "kmeans",
        "normalize_ht_features": True,
        "rank": 8,
        "action_pooling": 1.0,
        "obs_variance": 0.95,
    },
    fqi={"state_scaling": "predictive", "ensemble": 5, "centers": 100},
    turning_tpsr={"ht_dim": 20, "rank": 16, "action_pooling": 0.5},
)

PRESETS: Mapping[str, Preset] = MappingProxyType(
    {
        "best": _BEST,
        "predictive": dataclasses.replace(
            _BEST,
            name="predictive",
            summary="best made a predictive state: P_TH with the tests from the "
            "current step (so B_ao propagates the state it defines), histories of two "
            "images and a window at every step (overlapping), then the spectral model "
            "refined through its filter (at most 30 L-BFGS iterations on predicting the next "
            "10 images) from a start that carries 0.3 of the state forward at a typical step "
            "where the previous image helps to predict the next ones (a robot that turns: "
            "none, and an observation kernel widened to two effective centres); a diverged "
            "fitted-Q member is refitted alone",
            tpsr={
                **_BEST.tpsr,
                "p_th_tests": "from-current",
                "history_length": 2,
                "overlapping_episodes": True,
                "refine_epochs": 30,
                "refine_carry": 0.3,
                "refine_carry_rule": "aliased",
            },
            fqi={**_BEST.fqi, "refit": "member"},
            turning_tpsr={
                **_BEST.turning_tpsr,
                "refine_carry": 0.0,
                "obs_effective_centres": 2.0,
            },
        ),
        "guide": Preset(
            "guide",
            "the guide's settings: figure 4.5 with rank 5, fitted Q as in section 4.1 "
            "(robot bags: normalised history/test features)",
            robot_tpsr={"normalize_ht_features": True},
        ),
    }
)
"""Every preset by name."""

DEFAULT_PRESET = "predictive"
"""The preset of every command and of :func:`tpsr_ros.fit` unless another is named: on the
headline's fresh seeds at least level with ``best`` in every environment and above it in
``partial-strip`` (docs/results.md, "A predictive state")."""


TURN_COMPONENT = "angular.z"
"""The command component of a robot that turns (``cmd_vel``'s turn rate)."""


def turns(components: tuple[str, ...] | list[str]) -> bool:
    """Whether actions of these command components turn the robot (carry ``angular.z``).

    The components are those the actions vary in (constant ones are dropped when a
    codebook is learned), so a ``Twist`` stream whose ``angular.z`` is always 0 does not
    turn.
    """
    return TURN_COMPONENT in components


def get_preset(name: str) -> Preset:
    """The preset called ``name``; a ``ConfigError`` naming the choices otherwise."""
    try:
        return PRESETS[name]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None


def departures(config: TPSRConfig | FQIConfig, reference: TPSRConfig | FQIConfig) -> dict[str, Any]:
    """The fields of ``config`` whose values differ from ``reference``'s (a preset's config)."""
    return {
        f.name: getattr(config, f.name)
        for f in dataclasses.fields(config)
        if getattr(config, f.name) != getattr(reference, f.name)
    }
