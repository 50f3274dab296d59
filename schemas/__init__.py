"""Pydantic schemas of weldrecon: manifest, configs, ground truth, provenance."""
