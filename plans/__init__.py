"""Plan and workspace schemas, the global-input model, planners and example plans."""
