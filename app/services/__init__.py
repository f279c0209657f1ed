"""Business rules. Services take a session, query through SQLAlchemy and flush; the caller's
unit of work commits."""
