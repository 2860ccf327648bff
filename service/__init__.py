"""service: the verdict API (FastAPI) and the `noisestop` command line."""
