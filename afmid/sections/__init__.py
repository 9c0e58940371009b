"""Sections of the run config declared beside it, not in the stages that read them (docs/architecture.md,
Layers): ``coverage`` (``coverage:``, read by afmid.coverage), ``separation_track`` (``fit.separation_track``, read
by afmid.fit.separation_track), ``map_simulation`` (``simulate.map``, read by afmid.maps.simulate), ``scan``
(``simulate.scan``, read by afmid.simulate.scan), ``selection_scopes`` (the names of ``fit.selection_scope``, whose
strategy objects afmid.fit.selection_strategies registers against them). Schemas and declarations only: they
import nothing of afmid but the foundation (``registry``).
"""
