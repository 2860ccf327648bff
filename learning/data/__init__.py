"""The dataset: the stack format (`stack`, `exr`, `npz`), the virtual observer that labels it
(`observer`), checks (`check`), imports (`lisic`), synthetic stacks (`synthetic`), the half
buffers of a pass sequence (`accumulator`) and the one Mitsuba variant choice (`variant`).
"""
