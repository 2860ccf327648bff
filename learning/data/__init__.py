"""The dataset: the stack format (`stack` reads and validates, `stack_write` writes; `exr`,
`npz`), the virtual observer that labels it (`observer`), checks (`check`), imports
(`lisic`), synthetic stacks (`synthetic`), the half buffers of a pass sequence
(`accumulator`) and the one Mitsuba variant choice (`variant`).
"""
