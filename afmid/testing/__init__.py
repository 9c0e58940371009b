"""Reference implementations used by the tests only (not by the pipeline)."""
