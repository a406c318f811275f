"""A toy warpnerf plugin: the field ``toy_mlp`` and the dataset format ``toynpz``."""
