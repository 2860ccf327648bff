"""The stopping criteria the command line offers, in one home that imports nothing (the
parser is built without torch or Mitsuba and never keeps a copy)."""

CRITERIA = ("model", "flip", "variance", "uniform", "oracle")
#: what `noisestop render` and `make run` use unless told: the criterion that measured best
#: on the held-out scenes at <= 5 % early stops (README "Deciding a stop", BENCHMARKS.md)
DEFAULT_CRITERION = "flip"

