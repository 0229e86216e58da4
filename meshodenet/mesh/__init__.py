"""What every model sees of a case: the mesh and the trajectories as checked torch tensors, with
the training / validation splits (``data``), and the mesh's topology: directed edges, rod and
triangle hinges, the disjoint batch of many trajectories and a band ordering of the unknowns
(``graph``). Shared by the learners, the trainer and the model interface."""
