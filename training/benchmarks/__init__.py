"""Benchmarks of the training layer (``unipixie bench model``): the same form as :mod:`unipixie.core.benchmarks`,
whose timing helpers and writer of ``benchmarks/<name>.json`` they use; the root command line lists this package."""
