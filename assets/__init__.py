"""Dagster layer of Atlas-GS: thin software-defined assets over ``atlas_pipeline``.

``assets.definitions.defs`` is the one ``Definitions`` object (code location ``atlas_gs``).
"""

import warnings

from dagster import BetaWarning

# Beta features this layer relies on, on purpose (see assets/versioning.py): not worth a warning per use.
warnings.filterwarnings("ignore", category=BetaWarning, message=r".*(`data_version` of initializer `Output|"
                        r"`DataVersionsByPartition`|`observable_source_asset`|`include_sources`)")
