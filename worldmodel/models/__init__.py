"""Neural network models and learning algorithms of the pipeline (VAE, MDN-RNN, DDPG agent)."""
