"""The report stage: an offline HTML page and metrics.json for one capture (DESIGN sections 2, 5, 6).

Public API: :func:`make_report`, :class:`ReportSettings`, :class:`ReportError`.
"""

from recon.report.inputs import ReportError
from recon.report.stage import ReportSettings, make_report

__all__ = ["ReportError", "ReportSettings", "make_report"]
