"""Names and ranges of `learning` that the command line offers, in one home that imports
nothing, so the parser is built without torch or Mitsuba and never keeps a copy."""

#: inputs a feature model can be trained with: the content-free noise features of the half
#: buffers (`halves`, learning.inputs.noise_input), or the paper's quick-image difference with the
#: stack's own quick image (albedo), the extra direct-lighting image, or none (a flat image)
QUICK_MODES = ("halves", "albedo", "direct", "none")
#: the SVM kinds `train --model` trains (the paper's models, learning.training.train)
SVM_KINDS = ("svm", "dsvm", "svm_al", "dsvm_al", "svm_as", "dsvm_as")
#: the transfer-learning baselines `train --model` trains (learning.models.transfer_archs.ARCHS:
#: an ImageNet conv base + the paper's head; learning.training.train_transfer)
TRANSFER_KINDS = ("vgg19", "mobilenet_v2", "inception_v3", "resnet50", "densenet201")
#: every kind `train --model` accepts
MODEL_KINDS = SVM_KINDS + TRANSFER_KINDS
#: inputs a transfer baseline reads: the displayed noise picture of the half buffers
#: (`halves`) or the block itself (`none`, the paper's); it takes no quick image
TRANSFER_INPUTS = ("halves", "none")
#: the input `train` uses unless told (docs/guide/training.md "Model inputs")
DEFAULT_INPUT = "halves"
#: offsets a user, a request or a bundle may set are finite and at most this far from 0 (an
#: SVM's scores are a few units; an offset beyond any score only means "never" or "always",
#: but 1e300 or NaN in a request or a bundle means a mistake or an attack)
OFFSET_LIMIT = 1e6
#: the observer's noise target unless the user sets one (`--tau`, the HTTP `tau` parameter):
#: the largest 16x16-tile mean FLIP against the reference a converged block may show
DEFAULT_TAU = 0.02
