"""Fleet PKI: one CA per fleet, server certs for clones, client certs for robots, CRL."""
