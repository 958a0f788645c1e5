"""Session-wide: the tests train under the same thread default as the command line (see
posecorr.threads), so a busy machine does not make torch's threads wait on each other.
`make test` runs the files in two processes (pytest-xdist): each takes its share of the
cores, not all of them. Figures a test measures (corpus counts, conformance tallies) go
through the `summary` fixture to one section at the end of the run, which also works where
the test ran in another process (a worker's own output is not shown)."""
from __future__ import annotations

import pytest

SUMMARY = "summary"


class _Summary:
    """The summary lines of the run, read from each test's report (a worker's reports reach
    the controlling process with their user_properties)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def pytest_runtest_logreport(self, report) -> None:
        # each phase's report carries the test's whole list: the call phase's is the one read
        if report.when == "call":
            self.lines += [(report.nodeid, text) for key, text in report.user_properties if key == SUMMARY]

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if self.lines:
            terminalreporter.section("what the tests measured")
            for nodeid, text in sorted(self.lines):
                terminalreporter.write_line(f"{nodeid}:")
                for line in text.splitlines():
                    terminalreporter.write_line(f"  {line}")


def pytest_configure(config):
    import os
    import tempfile

    from posecorr.threads import set_threads

    set_threads(workers=int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")))
    # `fit --save` signs with the account's key (posecorr.saved): the tests, and the commands
    # they start, use a key of their own instead of the user's.
    os.environ["POSECORR_KEY_FILE"] = os.path.join(tempfile.mkdtemp(prefix="posecorr-key-"), "estimator.key")
    config.pluginmanager.register(_Summary(), "posecorr-summary")


# Files of more than a minute (`pytest --durations=60`: the session corpus, the proposal and
# report studies, the guides' outputs rerun, the CLI's training runs): collected first, so
# that the parallel run hands them out first and does not end on one of them alone.
LONG_FIRST = ("test_sessions.py", "test_propose.py", "test_report.py", "test_doc_outputs.py", "test_cli.py",
              "test_mlp.py")


def pytest_collection_modifyitems(items):
    def rank(item) -> int:
        name = item.path.name
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)
    items.sort(key=rank)   # stable: a file's tests keep their order and stay together


@pytest.fixture
def summary(request):
    """summary(text): a figure for the run's last section, under the test's name."""
    def add(text: str) -> None:
        request.node.user_properties.append((SUMMARY, text.strip("\n")))
    return add


@pytest.fixture(scope="module")
def workspace_poses():
    """40 poses around the workspace centre, orientations up to about 1 rad from identity:
    the poses the effects' and forms' formula tests run on."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    p = np.array([0.0, -0.6, 0.5]) + rng.uniform(-0.25, 0.25, (40, 3))
    R = Rotation.from_rotvec(rng.normal(scale=0.6, size=(40, 3))).as_matrix()
    return p, R
