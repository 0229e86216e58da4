"""Training shared by every model: the engine (``train``: ``TrainConfig``, ``fit``, checkpoints
and their safe loading, histories, budgets), its multi-process data parallelism
(``distributed``) and the presets and config checks every model's presets are built from
(``presets``: the paper's optimiser and schedules, ``quick`` and ``smoke``)."""
