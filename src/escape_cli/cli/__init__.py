"""The `escape` command line."""
