"""Evaluation: the paper's correspondence metric per step, tables over steps and seeds,
and the HTML report. Reads models and sequences; never changes them."""
