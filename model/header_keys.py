"""The ``gradsep.*`` header keys that carry meaning between the renderer, the reconstruction and an answer.

Standard library only. A frame's other string attributes travel with it unchanged (model/exr_read.py reads them,
model/exr_write.py's :func:`~gradsep.model.exr_write.encode_answer` writes them back); these keys are the ones an
answer writes itself, or the render plan's prediction that an answer carries only when it still holds.
"""

from __future__ import annotations

#: The OIDN setting (model.oidn.SETTINGS) a render plan asks its frame to be reconstructed with, and, on an answer,
#: the one that ran (model.oidn.frame_setting).
OIDN_SETTING_KEY = "gradsep.oidn_setting"
#: Keys an answer writes itself: the input's values for them are not carried over.
ANSWER_KEYS = frozenset({"gradsep.method", "gradsep.layers", "gradsep.alpha", "gradsep.warnings",
                         "gradsep.request_id", "gradsep.source", "gradsep.channels", OIDN_SETTING_KEY})
WARNINGS_ATTRIBUTE = "gradsep.warnings"
WARNINGS_LIMIT = 2000  # characters of gradsep.warnings in the header
#: A planned render's predicted RelMSE after reconstruction with ``PLAN_METHOD_KEY`` (renderer/planned_frame.py writes
#: both). An answer carries the prediction only when it was reconstructed with that method: for another method
#: it would state some other method's error.
PREDICTED_RELMSE_KEY = "gradsep.predicted_relmse"
PLAN_METHOD_KEY = "gradsep.plan_method"
#: Where the prediction comes from (``frame``: the frame's own halves, renderer/check.py; ``pilot``) and the
#: frame check's figures (JSON: per half its samples, estimated RelMSE and standard error; the error-vs-spp
#: exponent it was carried with; the check's seconds and what the render held back for it). Both describe
#: PREDICTED_RELMSE_KEY and travel with it.
PREDICTED_FROM_KEY = "gradsep.predicted_from"
CHECK_KEY = "gradsep.frame_check"
PREDICTION_KEYS = (PREDICTED_RELMSE_KEY, PREDICTED_FROM_KEY, CHECK_KEY)
