"""What a model sees of a block: the half-buffer input and the `flip` score (`halves`,
`noise_input`), and every (scene, level, block) of a dataset as one row, cached (`table`).
"""
