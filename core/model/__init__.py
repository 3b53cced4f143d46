"""The UniPixie model (grid encoder, flow-matching decoders) and its inference path."""
