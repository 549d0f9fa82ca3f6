"""kftune.optim."""
