"""Training of the learned BEV detector in the simulator (``roco-env train-detector``).

``data`` draws training/validation scenes from the scenario library, ``train``
runs the deterministic training loop and validation, ``report`` writes the
loss curves and metrics. Sits above the environment stages it uses (traffic,
sensing, fusion, evaluation); needs torch.
"""
