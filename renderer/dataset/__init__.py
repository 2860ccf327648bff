"""Dataset building: a scene's labelled stack (`stackbuild`), many scenes on a pool or farm
(`build`), and a stack's contact sheet (`contact`)."""
