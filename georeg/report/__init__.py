"""Evaluation against truth, figures and the HTML report."""
