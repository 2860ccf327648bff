"""The scene library: the built-in scenes (`catalog` lists them), their kit, and the loading
and checking of scene files."""
