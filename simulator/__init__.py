"""A simulated scanning cell: specimen, stickers, fixture, robot and line scanner, with ground truth.

Writes exactly what a real cell writes (manifest + pass stores); the pipeline never imports it.
"""
