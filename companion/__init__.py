"""Companion computer of an aerial skeleton: SCKF constraint application and its tools.

``companion.estimation`` is the pure estimation core (numpy/scipy only).
"""
