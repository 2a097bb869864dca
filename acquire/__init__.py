"""acquire: hardware drivers (stage, cameras), their simulated twins and the capture plan."""
