"""The report: HTML pages, figures and summary.json from run files."""
