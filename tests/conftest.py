"""Session-wide: the tests train under the same thread default as the command line (see
posecorr.threads), so a busy machine does not make torch's threads wait on each other."""
from __future__ import annotations


def pytest_configure(config):
    import os
    import tempfile

    from posecorr.threads import set_threads

    set_threads()
    # `fit --save` signs with the account's key (posecorr.saved): the tests, and the commands
    # they start, use a key of their own instead of the user's.
    os.environ["POSECORR_KEY_FILE"] = os.path.join(tempfile.mkdtemp(prefix="posecorr-key-"), "estimator.key")
