"""One module per stored component of a .nbvh file, each writing its tensors and reading them back: `bvh` (the
node tree), `table` (feature tables and HashVQAD's index), `network` (the MLP/KMLP), `look` (appearance head and
textures). Each writer returns (name, component, bytes, shape) rows in file order; `fileformat` lays them out."""
