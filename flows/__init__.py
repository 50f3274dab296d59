"""Prefect flows, thin task wrappers and the command-line interface."""
