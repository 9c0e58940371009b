"""Reading a record: readers, the Trace, and the checks on load (defects, onset, inspect)."""
