"""The inspection report to sign: one PDF per done inspection (``GET /api/v1/inspections/{id}/report.pdf``).

Built with ReportLab: pure Python (no browser, TeX or system fonts to install on a cell PC), long
maintained, and its platypus layer flows paragraphs and tables over A4 pages while its canvas draws
the page header, the deviation map with its colour bar and callouts, and the gap profiles. The
report is built from plain data (:class:`ReportData`: the inspection's API document, its target,
capture record, calibrations and artifact folder); :mod:`app.services.reports` gathers it, this
package only draws: :mod:`~app.report.document` (the pages), :mod:`~app.report.header` (every
page's header and "Page X of Y"), :mod:`~app.report.tables`, :mod:`~app.report.figures` and
:mod:`~app.report.text` (numbers, times, "not recorded").
"""

from app.report.document import ReportData, build_report, report_number

__all__ = ["ReportData", "build_report", "report_number"]
