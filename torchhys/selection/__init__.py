"""Model selection on tensors: which model family fits a record, chosen by cross-validation."""
