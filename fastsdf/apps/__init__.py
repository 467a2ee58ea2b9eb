"""Applications on top of the library: the command line, the demo, particles sharded over Dask."""

__all__: list[str] = []
