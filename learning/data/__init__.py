"""The dataset: the stack format (`stack_format` names its files, `stack` reads,
`stack_validate` checks meta.json, `stack_write` writes, `dataset_dir` finds the stacks of a
directory; `exr`, `npz`), the virtual observer that labels it (`frame_flip` runs FLIP,
`block_terms` and `tile_terms` pool it, `observer` thresholds it, `relabel` makes stored
labels its own), checks (`check`), imports (`lisic`), synthetic stacks (`synthetic`), the
half buffers of a pass sequence (`accumulator`) and the one Mitsuba variant choice
(`variant`).
"""
