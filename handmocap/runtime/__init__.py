"""The graph runtime: bus, codec, node, launch, executor, bags, command lines, frames, Foxglove, keys."""
