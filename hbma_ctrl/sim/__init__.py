"""The plant: trials and their inputs, the batch simulator with its hybrid events, the protocol's trials,
and the mismatched rig every single-chamber estimator and controller is judged against.
"""
