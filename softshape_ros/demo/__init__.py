"""The end-to-end demo on the simulated rig (``softshape demo``, ``make demo``)."""
