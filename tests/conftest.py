"""Test-session settings: one BLAS thread per test process.

``make test`` runs the suite in parallel (pytest-xdist, one worker per core), so BLAS
threads would only fight over the same cores: a whitening test that takes 3 s alone took
19 s under contention. The environment variables reach the subprocesses the tests start
(nodes, commands); threadpoolctl limits the BLAS already loaded in this process.
"""

from __future__ import annotations

import os

import pytest

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"


def pytest_configure(config: object) -> None:
    """Limit the BLAS of this process to one thread (numpy may be imported already)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)


@pytest.fixture
def ros_env(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """This process and its children: a ROS domain of their own, loopback, default backend."""
    from graph_support import fresh_domain

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain()))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.delenv("TPSR_TRANSPORT", raising=False)
    monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    return dict(os.environ)
