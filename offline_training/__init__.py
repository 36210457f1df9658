"""Command-line programs that train, evaluate and refit StARS checkpoints."""
