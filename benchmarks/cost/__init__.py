"""The cost benchmark (``meshbench bench``): the training and rollout throughput of MeshODENet's
implementations (``enginebench``), against a stand-in for the authors' training code
(``authors_style``), Implicit-Energy against the solver it stands in for (``energybench``), the
device's clocks and peak memory (``device``), and the report and baseline comparison of a result
(``report``)."""
