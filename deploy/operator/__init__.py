"""A real fleet (operators): one robot's agent config and service (``agent_config``,
``agent_service``), a fleet's keys, certificates and access control (``fleet_init``,
``certificates``, ``access_control``), the live fleet session and view (``fleet_session``,
``fleet_view``) and journal replay (``replay``). It imports ``deploy.study`` and ``deploy.base``
only of ``deploy``."""
