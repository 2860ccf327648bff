"""The stopping criteria the command line offers, in one home that imports nothing (the
parser is built without torch or Mitsuba and never keeps a copy)."""

CRITERIA = ("model", "flip", "variance", "uniform", "oracle")
#: what `noisestop render` and `make run` use unless told: the criterion that measured best
#: on the held-out scenes at <= 5 % early stops (README "Deciding a stop", BENCHMARKS.md)
DEFAULT_CRITERION = "flip"


def criterion_name(criterion: object = None, *, model: object = None, server: object = None,
                   offset: object = None) -> object:
    """The criterion a render uses, on every door (API, command line, plugin): the one
    given; else ``model`` when a model bundle, a verdict server or an offset is given (each
    means something to the model criterion only); else DEFAULT_CRITERION."""
    if criterion is not None:
        return criterion
    return "model" if model is not None or server is not None or offset is not None else DEFAULT_CRITERION
