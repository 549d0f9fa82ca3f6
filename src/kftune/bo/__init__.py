"""kftune.bo."""
