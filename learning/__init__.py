"""learning: dataset format, virtual observer, models, Algorithm 1, metrics, model bundles."""
from .check import Problem, check_dataset
from .lisic import import_lisic
from .observer import VirtualObserver, label_stack
from .stack import Stack, StackWriter, list_stacks, make_plan, read_stack, update_labels, write_stack
from .synthetic import make_synthetic_stack

__all__ = ["Stack", "StackWriter", "read_stack", "write_stack", "make_plan", "list_stacks",
           "update_labels", "VirtualObserver", "label_stack", "check_dataset", "Problem",
           "import_lisic", "make_synthetic_stack"]
