"""Dagster layer of Atlas-GS: thin software-defined assets over ``atlas_pipeline``.

``assets.definitions.defs`` is the one ``Definitions`` object (code location ``atlas_gs``).
"""
