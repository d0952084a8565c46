"""Alerts for failed swathflow runs: a Prefect webhook notification block and an automation.

    PREFECT_API_URL=http://127.0.0.1:14200/api python deploy/prefect/alerts.py WEBHOOK_URL

Saves a ``CustomWebhookNotificationBlock`` named ``swathflow-alerts`` that POSTs
``{"text": "<subject>\\n<body>"}`` to WEBHOOK_URL (a Slack/Teams/Mattermost incoming
webhook accepts that shape), and an automation ``swathflow: run failed`` that fires on every
``prefect.flow-run.Failed`` event of the swathflow-inbox or swathflow-mission flows and
sends the flow, run name and the state message (for the inbox: every failed mission and
its reason). Running it again replaces both. Prints the automation's id.
"""
from __future__ import annotations

import sys

from prefect.automations import Automation
from prefect.blocks.notifications import CustomWebhookNotificationBlock
from prefect.events.actions import SendNotification
from prefect.events.schemas.automations import EventTrigger, Posture

NAME = "swathflow: run failed"
FLOWS = ["swathflow-inbox", "swathflow-mission"]


def install(url: str, block_name: str = "swathflow-alerts") -> Automation:
    """Create (or replace) the webhook block and the automation; returns the automation."""
    block = CustomWebhookNotificationBlock(name="swathflow", url=url, method="POST",
                                           json_data={"text": "{{subject}}\n{{body}}"})
    block_id = block.save(block_name, overwrite=True)
    try:
        Automation.read(name=NAME).delete()
    except ValueError:  # none yet
        pass
    return Automation(
        name=NAME,
        description="Tell the operators when an inbox run or a mission fails.",
        trigger=EventTrigger(
            expect={"prefect.flow-run.Failed"},
            match_related={"prefect.resource.role": "flow", "prefect.resource.name": FLOWS},
            posture=Posture.Reactive, threshold=1, within=0),
        actions=[SendNotification(
            block_document_id=block_id,
            subject="swathflow: {{ flow.name }} run {{ flow_run.name }} failed",
            body="{{ flow_run.state.message }}")],
    ).create()


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    print(install(sys.argv[1]).id)
