"""The application: map sessions, replay, data sources."""
