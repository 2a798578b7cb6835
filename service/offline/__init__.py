"""Offline tools: the replay (through the same map pipeline as the service), a client
of the REST API, datasets and simulators, and trajectory evaluation. Used by the
`covslam` command and bench/, never by the running service."""
