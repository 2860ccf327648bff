"""Workflows: train one model (`train`); train many and compare them (`compare`,
`compare_inputs`, `knobs`).
"""
