"""Everything that touches storage: pass stores, manifests, hashes, atomic writes."""
