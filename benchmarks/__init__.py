"""meshbench glue: the command-line interface (``cli``, ``commands``), the suite (``suite``),
ground-truth validation (``validation``) and the engine benchmark (``engine``)."""
