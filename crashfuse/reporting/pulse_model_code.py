"""The code MLflow logs as a final model's pyfunc ("models from code": no pickle in the model)."""

from mlflow.models import set_model

from crashfuse.reporting.served import PulseModel

set_model(PulseModel())
