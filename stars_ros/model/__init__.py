"""The StARS model: typed configs, encoders, the torch model and its training, checkpoints,
and the numpy serving form the node and the fold-in score with."""
