"""The diagnosis: where the model fails and which physical effect (or instrument) is missing."""
