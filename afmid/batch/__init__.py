"""Many items: plan, execution engines (local pool, dask.distributed) and the summary."""
