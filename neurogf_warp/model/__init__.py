"""The model: the torch network, the Model type (network + frame + mesh), model files."""
