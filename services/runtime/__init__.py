"""What every service process shares at run time: the process scaffolding (service.py: logging,
signals, inboxes, deadlines), the Zenoh session configuration (zconf.py) and the run's identities
(security.py: mutual-TLS certificates and the router's ACL). Services and the launcher (deploy/)
import it; it imports neither."""
