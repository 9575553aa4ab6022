"""jaxfog's benchmarks (not part of the installed package): run from the repository root as
`python -m benchmarks.bench`, `python -m benchmarks.bench_grad`, `python -m benchmarks.bench_profile`, ...;
`benchmarks.bench_mitsuba` is the Mitsuba 3 side that `benchmarks.bench` and `benchmarks.bench_cost` run in a
subprocess; `python -m benchmarks.bench_cycles` compares with Blender Cycles, whose side
(`benchmarks/cycles_render.py`) runs in its own interpreter with `bpy`. The harness they share (timing, interleaved
A/B runs, machine records, JSON output, tables): `benchmarks.common`. Raw output goes to `bench_out/` (or `--out`);
the curated results and the commands that made them: `docs/results/`."""
