"""Test set-up shared by all suites.

bpy is imported first: pymeshlab and bpy both bundle Embree, and bpy fails to import after pymeshlab.
"""
import bpy  # noqa: F401  (must precede any pymeshlab import)
import matplotlib

matplotlib.use("Agg")
