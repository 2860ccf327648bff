"""The offline simulation: the live loop's `PassLoop` replayed on stored stacks (`simulate`)."""
