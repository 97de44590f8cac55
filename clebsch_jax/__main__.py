"""`python -m clebsch_jax`: the `clebsch-jax` command line (see `clebsch_jax.cli`)."""

from .cli import main

if __name__ == "__main__":
    raise SystemExit(main())
