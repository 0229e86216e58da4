"""The engine benchmark: training throughput of the implementations (``meshbench bench``)."""
