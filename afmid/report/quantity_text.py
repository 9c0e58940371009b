"""The report's name for :mod:`afmid.quantity_text` (numbers in human units), which moved to the foundation
layer so the fit and the diagnosis write with it without importing the report (docs/architecture.md, Layers)."""

from afmid.quantity_text import (  # noqa: F401 (re-exported for the report's modules)
    CI95_LABEL,
    SIGMA_LABEL,
    display_unit,
    format_delta_bic,
    format_interval,
    format_measurement,
    format_number,
    format_value,
    pdg_error_digits,
)
