"""``python -m learner``: see :mod:`learner.cli`."""

from learner.cli import entry

entry()
