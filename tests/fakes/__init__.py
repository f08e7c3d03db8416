"""In-memory fakes of cloud APIs for the provider tests."""
