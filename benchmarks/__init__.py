"""meshbench glue: registries, data generation, the runner and the command-line interface."""
