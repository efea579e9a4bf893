"""Studies: sweeps of planner cases and campaigns of emulated runs, run on Dask distributed.

`spec` reads a study (TOML: what each case runs, its parameters, its seeds), `cases` runs one case,
`execution` runs them all (a LocalCluster, a lab's scheduler, or serially), `table` keeps the
results (one Parquet table, a row per case), `report` draws them, `cli` is `rigctl study`.
"""
