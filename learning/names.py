"""Names and ranges of `learning` that the command line offers, in one home that imports
nothing, so the parser is built without torch or Mitsuba and never keeps a copy."""

#: inputs a feature model can be trained with: the content-free noise features of the half
#: buffers (`halves`, learning.inputs.noise_input), or the paper's quick-image difference with the
#: stack's own quick image (albedo), the extra direct-lighting image, or none (a flat image)
QUICK_MODES = ("halves", "albedo", "direct", "none")
#: the SVM kinds `train --model` trains (the paper's models, learning.training.train)
SVM_KINDS = ("svm", "dsvm", "svm_al", "dsvm_al", "svm_as", "dsvm_as")
#: the input `train` uses unless told (README "Model inputs")
DEFAULT_INPUT = "halves"
#: offsets a user, a request or a bundle may set are finite and at most this far from 0 (an
#: SVM's scores are a few units; an offset beyond any score only means "never" or "always",
#: but 1e300 or NaN in a request or a bundle means a mistake or an attack)
OFFSET_LIMIT = 1e6
