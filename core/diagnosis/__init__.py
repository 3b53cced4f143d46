"""Comparing simulations with measurements and finding the missing physical effect."""
