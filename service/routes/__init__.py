"""The service's HTTP and WebSocket routes, one router per concern: sessions, ingest, events, library, ops."""
