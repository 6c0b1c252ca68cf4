"""The learner node: learns the TPSR and its fitted-Q policy while the robot runs.

    python -m tpsr_ros.learner_node --ros-args -p output:=DIR [-p warmup_steps:=N]
        [-p refit_steps:=N]

It makes steps of the simulator's live topics as ``learner fit`` reads a recording of
them, refits in a worker process at the end of a warm-up and then every ``refit_steps``
steps, writes each version atomically to ``DIR`` and announces it on the latched
``tpsr/model_update``, which the filter node swaps in (msgs_doc/learner_node.md is the
interface). Its parts:

- :mod:`~tpsr_ros.learner_node.refits`: one refit, free of ROS: steps in, files out;
- :mod:`~tpsr_ros.learner_node.node`: the parameters and the node around it.

Names are imported on first use, so importing the ROS-free part does not load the node.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tpsr_ros.lazy import lazy_exports

_API = {
    "LearnerNode": "tpsr_ros.learner_node.node",
    "LearnerNodeParams": "tpsr_ros.learner_node.node",
    "PROG": "tpsr_ros.learner_node.node",
    "main": "tpsr_ros.learner_node.node",
    "RefitRequest": "tpsr_ros.learner_node.refits",
    "RefitResult": "tpsr_ros.learner_node.refits",
    "refit": "tpsr_ros.learner_node.refits",
}

__all__ = ["PROG", "LearnerNode", "LearnerNodeParams", "RefitRequest", "RefitResult", "main",
           "refit"]

if TYPE_CHECKING:
    from tpsr_ros.learner_node.node import PROG, LearnerNode, LearnerNodeParams, main
    from tpsr_ros.learner_node.refits import RefitRequest, RefitResult, refit


__getattr__, __dir__ = lazy_exports(__name__, _API, __all__)
