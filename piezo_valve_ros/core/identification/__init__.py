"""Identification and the residual loop: records, the effect catalogue, the analysis and its report, and the
model it hands to the controller."""
from __future__ import annotations

from .. import lazy_exports

__all__, __getattr__ = lazy_exports(__name__, {
    "analyse": "residual",
    "Analysis": "residual",
    "Record": "records",
    "read_csv": "records",
    "IdentificationError": "records",
    "HELD_OUT_FRACTION": "records",
    "MAX_ANALYSED_S": "records",
    "BlockMeans": "whole_record",
    "whole_residual": "whole_record",
    "trend_search": "whole_record",
    "CATALOGUE": "effects",
    "compensation": "to_controller",
    "Compensation": "to_controller",
    "IdentificationReport": "report",
    "check_report": "report",
})
