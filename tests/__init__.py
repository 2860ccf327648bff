"""noisestop's tests, grouped by the package they exercise (noisefeat, learning, renderer,
service), plus cli (the command line and end-to-end runs across packages) and project
(layout and documentation rules). Shared helpers live in `tests.support`; shared set-up in
conftest.py."""
