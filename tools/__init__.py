"""Build harnesses run from a checkout (`make models`); not part of the installed package."""
