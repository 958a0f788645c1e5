"""`python -m posecorr VERB ...`: the `posecorr` command, where the venv's bin is not on PATH."""
import sys

from posecorr.cli import main

sys.exit(main())
