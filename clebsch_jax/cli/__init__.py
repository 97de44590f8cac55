"""The `clebsch-jax` command line, its scenes and the Figure 1 demo: the library's front end.

Built on the public API only (`import clebsch_jax as cj`), like any program using the library:

- `_commands`: the parser and its subcommands (`main`): `_demo_command` (`demo`),
  `_run_command` (`run SCENE`), `_bench_command` (`bench`), `_sweep` (`sweep`), on the parsing
  of `_arguments`, the setup of `_setup` (output folder, matplotlib, compilation cache, `fail`),
  the progress bar of `_progress` and the terminal tables of `_tables`;
- `_scenes`: the built-in scenes of `run` and `demo`, as data (`SCENES`), defined by family in
  `_scenes_bodies`, `_scenes_particles` and `_scenes_fluid` on the types of `_scene_types`;
- `_scene_run`: the chunked run that reduces a scene's batch to its tallies, and
  `_scene_report` its summary and plot;
- `_demo`: the scene of Figure 1 of the paper (the rigid body of Example 30);
- `_sweep`: the subcommand `sweep` (a TOML-described `clebsch_jax.sweep` into a Zarr store).

`python -m clebsch_jax`, `python -m clebsch_jax.cli` and the `clebsch-jax` script all run `main`.
"""

from ._commands import main

__all__ = ["main"]
