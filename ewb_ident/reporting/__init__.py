"""Text summaries, figures and the HTML validation report."""
