"""Session-wide: the tests train under the same thread default as the command line (see
posecorr.threads), so a busy machine does not make torch's threads wait on each other."""
from __future__ import annotations


def pytest_configure(config):
    from posecorr.threads import set_threads

    set_threads()
