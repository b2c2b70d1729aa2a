"""`python -m rbdyn_jax.cli`: the `rbdyn` command."""

import sys

from . import main

if __name__ == "__main__":
    sys.exit(main())
