"""Atlas-GS: RGB-D observations in, a persistent 3D Gaussian world out.

The library is orchestrator-agnostic: nothing here imports Dagster. The Dagster layer lives in the
top-level ``assets`` package and only calls into these modules.
"""

__version__ = "0.1.0"
