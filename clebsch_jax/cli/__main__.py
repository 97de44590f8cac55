"""`python -m clebsch_jax.cli`: the `clebsch-jax` command line."""

from . import main

if __name__ == "__main__":
    raise SystemExit(main())
