"""The FMI 3.0 co-simulation wrapper (placeholder until written)."""

FMI3 = ""
