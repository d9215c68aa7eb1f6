"""The passport document, its registry (storage and integrity) and the provenance of its inputs."""
