"""`ccrp dashboard`: the fleet in a browser, live (docs/dashboard.md). FastAPI and uvicorn are
imported only by this package, which only the `dashboard` command imports."""
