"""The learning side of the pipeline (torch): data, models and one module per stage."""
