"""
Experiments that need both learning and physics, one floor above ``model/`` and ``sim/``.

``model/`` reads datasets and knows no simulator; ``sim/`` knows nothing of learning. What
asks the simulator a question and the model the same one lives here: the object-distance
sweep of the paper's Fig. 4(c) (:mod:`.distance_sweep`), the reproduction that ends with it
(:mod:`.reproduction`) and the pre-training that simulates its data (:mod:`.pretrain`).
"""
