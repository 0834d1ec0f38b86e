"""The plant historian: drive states from zenoh into PostgreSQL, with an on-disk buffer (docs/historian.md)."""
