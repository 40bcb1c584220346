"""Benchmarks that print figures: ``python -m sitl.bench table2|scaling|zenoh`` (see ``--help``)."""
