"""The dashboard's sections, one module per page, each section a function from runs / params to an HTML fragment:
:mod:`~dashboards.sections.runs` (overview and the run list), :mod:`~dashboards.sections.tables`,
:mod:`~dashboards.sections.curves`, :mod:`~dashboards.sections.claims`, :mod:`~dashboards.sections.codebooks`,
:mod:`~dashboards.sections.quality`, :mod:`~dashboards.sections.videos`; :mod:`~dashboards.sections.common` holds
what they share.

Runs come newest first (:func:`m3t.experiment.fetch_runs`). A section with nothing to show says which stage or
command produces its content instead.
"""
