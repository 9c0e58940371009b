"""Sections of the run config declared beside it, not in the stages that read them (docs/architecture.md,
Layers): ``coverage`` (``coverage:``, read by afmid.coverage), ``separation_track`` (``fit.separation_track``, read
by afmid.fit.separation_track), ``map_simulation`` (``simulate.map``, read by afmid.maps.simulate), ``scan``
(``simulate.scan``, read by afmid.simulate.scan). Pydantic schemas only: they import nothing of afmid.
"""
