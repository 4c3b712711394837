"""Progress bars live in xyzcyl.common.progress (the client uses them too).

Kept only for model_export/train.py, evaluate.py and data/synth.py, which the camera-type refactor (issue 27,
house 1) is rewriting: switch their import lines to xyzcyl.common.progress, then delete this module."""

from xyzcyl.common.progress import is_terminal, progress_bar  # noqa: F401
