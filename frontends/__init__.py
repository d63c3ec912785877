"""Front-end plugins: compositions of the slam/ building blocks (see pyproject entry points)."""
